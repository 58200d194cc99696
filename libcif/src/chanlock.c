/* chanlock.c - see chanlock.h. */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include "chanlock.h"

#include <errno.h>
#include <fcntl.h>
#include <sys/file.h>
#include <time.h>
#include <unistd.h>

#define FLOCK_RETRY_NS 200000L /* as host_api/locks.py */

long long cifemu_now_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

int cifemu_chanlock_open(cifemu_chanlock *lock, const char *path) {
  lock->fd = open(path, O_RDWR | O_CREAT | O_CLOEXEC, 0660);
  if (lock->fd < 0) return -1;
  pthread_mutex_init(&lock->mutex, NULL);
  return 0;
}

void cifemu_chanlock_close(cifemu_chanlock *lock) {
  if (lock->fd >= 0) {
    close(lock->fd);
    pthread_mutex_destroy(&lock->mutex);
  }
  lock->fd = -1;
}

static unsigned long long clamp_ms(unsigned long ms) {
  /* about 24 days at most: a deadline that fits every clock [ours] */
  return ms > 2000000000UL ? 2000000000ULL : (unsigned long long)ms;
}

int cifemu_chanlock_acquire(cifemu_chanlock *lock, unsigned long timeout_ms) {
  if (pthread_mutex_trylock(&lock->mutex) == 0) { /* the uncontended case, without clocks */
    if (flock(lock->fd, LOCK_EX | LOCK_NB) == 0) return 1;
    pthread_mutex_unlock(&lock->mutex);
  } else {
    struct timespec until;
    unsigned long long ms = clamp_ms(timeout_ms);
    if (ms == 0) return 0;
    clock_gettime(CLOCK_REALTIME, &until);
    until.tv_sec += (time_t)(ms / 1000);
    until.tv_nsec += (long)(ms % 1000) * 1000000L;
    if (until.tv_nsec >= 1000000000L) {
      until.tv_sec += 1;
      until.tv_nsec -= 1000000000L;
    }
    if (pthread_mutex_timedlock(&lock->mutex, &until) != 0) return 0;
  }
  if (cifemu_flock_acquire(lock->fd, timeout_ms)) return 1;
  pthread_mutex_unlock(&lock->mutex);
  return 0;
}

int cifemu_flock_acquire(int fd, unsigned long timeout_ms) {
  struct timespec pause = {0, FLOCK_RETRY_NS};
  long long deadline = cifemu_now_ns() + (long long)clamp_ms(timeout_ms) * 1000000LL;
  for (;;) {
    if (flock(fd, LOCK_EX | LOCK_NB) == 0) return 1;
    if ((errno != EWOULDBLOCK && errno != EINTR) || cifemu_now_ns() >= deadline) return 0;
    nanosleep(&pause, NULL);
  }
}

void cifemu_chanlock_take(cifemu_chanlock *lock) {
  pthread_mutex_lock(&lock->mutex);
  while (flock(lock->fd, LOCK_EX) != 0 && errno == EINTR) {
  }
}

void cifemu_chanlock_release(cifemu_chanlock *lock) {
  flock(lock->fd, LOCK_UN);
  pthread_mutex_unlock(&lock->mutex);
}
