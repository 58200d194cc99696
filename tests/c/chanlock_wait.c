/*
 * chanlock_wait.c - libcif's channel lock (libcif/src/chanlock.c, compiled in) against
 * another host holding its flock (tests/test_libcif_hosts.py).
 *
 * 1. Four threads want the channel while another open file description of the lock file
 *    (another host) holds the flock: once it lets go, they must enter one at a time.
 * 2. A caller's whole wait is its time-out: a thread waiting for the mutex, which then
 *    finds the flock taken by another host, gives up at its time-out, not later.
 *
 * Usage: chanlock_wait LOCKFILE
 */
#include "chanlock.c"
#include "holder.c"

#include <stdio.h>

#define THREADS 4
#define ROUNDS 20

static cifemu_chanlock lock;
static int inside, most_inside, trying, entered;

static void *enter(void *unused) {
  int n;
  struct timespec hold = {0, 200000};
  (void)unused;
  __atomic_fetch_add(&trying, 1, __ATOMIC_SEQ_CST);
  if (!cifemu_chanlock_acquire(&lock, 5000)) return NULL;
  n = __atomic_add_fetch(&inside, 1, __ATOMIC_SEQ_CST);
  if (n > __atomic_load_n(&most_inside, __ATOMIC_SEQ_CST))
    __atomic_store_n(&most_inside, n, __ATOMIC_SEQ_CST);
  nanosleep(&hold, NULL); /* inside: a mailbox copy takes this long at most */
  __atomic_sub_fetch(&inside, 1, __ATOMIC_SEQ_CST);
  __atomic_fetch_add(&entered, 1, __ATOMIC_SEQ_CST);
  cifemu_chanlock_release(&lock);
  return NULL;
}

static long long ms_since(long long start) { return (cifemu_now_ns() - start) / 1000000LL; }

static void *late_waiter(void *result) {
  long long start = cifemu_now_ns();
  int got = cifemu_chanlock_acquire(&lock, 500);
  *(long long *)result = got ? -1 : ms_since(start);
  if (got) cifemu_chanlock_release(&lock);
  return NULL;
}

int main(int argc, char **argv) {
  pthread_t thread[THREADS], waiter;
  struct timespec step = {0, 1000000}, contended = {0, 20000000}, held = {0, 300000000};
  long long waited = 0;
  int other, round, i;
  if (argc != 2 || cifemu_chanlock_open(&lock, argv[1]) != 0) return 2;
  other = open(argv[1], O_RDWR | O_CLOEXEC);
  if (other < 0) return 2;
  for (round = 0; round < ROUNDS; round++) {
    __atomic_store_n(&trying, 0, __ATOMIC_SEQ_CST);
    flock(other, LOCK_EX);
    for (i = 0; i < THREADS; i++) pthread_create(&thread[i], NULL, enter, NULL);
    while (__atomic_load_n(&trying, __ATOMIC_SEQ_CST) < THREADS) nanosleep(&step, NULL);
    nanosleep(&contended, NULL); /* the other host keeps the channel a little longer */
    flock(other, LOCK_UN);
    for (i = 0; i < THREADS; i++) pthread_join(thread[i], NULL);
  }
  if (most_inside != 1 || entered != THREADS * ROUNDS) {
    fprintf(stderr, "chanlock_wait: %d threads inside at once, %d of %d entered\n", most_inside,
            entered, THREADS * ROUNDS);
    return 1;
  }
  /* 2: this thread holds the channel for 300 ms while the waiter (500 ms) waits for the
     mutex; as the channel is let go, another host takes its flock and keeps it. */
  if (!cifemu_chanlock_acquire(&lock, 0)) return 2;
  pthread_create(&waiter, NULL, late_waiter, &waited);
  nanosleep(&held, NULL);
  flock(lock.fd, LOCK_UN);
  flock(other, LOCK_EX);
  pthread_mutex_unlock(&lock.mutex);
  pthread_join(waiter, NULL);
  flock(other, LOCK_UN);
  if (waited < 0 || waited > 650) {
    fprintf(stderr, "chanlock_wait: a 500 ms time-out waited %lld ms (-1: got the channel)\n",
            waited);
    return 1;
  }
  cifemu_chanlock_close(&lock);
  close(other);
  printf("chanlock_wait: one thread inside at a time; a 500 ms time-out waited %lld ms\n", waited);
  return 0;
}
