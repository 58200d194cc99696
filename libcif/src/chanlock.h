/*
 * chanlock.h - one board channel's lock, shared with Python hosts (host_api/locks.py).
 *
 * A thread mutex serialises this process's threads; an flock on
 * <dir>/board<N>.<channel>.lock serialises processes, C and Python alike. A caller
 * waits for the channel up to its own timeout; the driver then answers -4.
 */
#ifndef CIFEMU_CHANLOCK_H
#define CIFEMU_CHANLOCK_H

#include <pthread.h>

typedef struct cifemu_chanlock {
  pthread_mutex_t mutex;
  int fd;
} cifemu_chanlock;

int cifemu_chanlock_open(cifemu_chanlock *lock, const char *path);
void cifemu_chanlock_close(cifemu_chanlock *lock);
/* 1 when taken within timeout_ms (0: only if free now), else 0. */
int cifemu_chanlock_acquire(cifemu_chanlock *lock, unsigned long timeout_ms);
/* Blocks: for locks held only for microseconds (the DevFlags read-modify-write). */
void cifemu_chanlock_take(cifemu_chanlock *lock);
void cifemu_chanlock_release(cifemu_chanlock *lock);

/* The flock alone, within timeout_ms: 1 taken, 0 not (for locks held across calls). */
int cifemu_flock_acquire(int fd, unsigned long timeout_ms);

long long cifemu_now_ns(void); /* CLOCK_MONOTONIC */

#endif
