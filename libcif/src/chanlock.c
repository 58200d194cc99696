/* chanlock.c - see chanlock.h. */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include "chanlock.h"
#include "dpm.h"
#include "holder.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#define FLOCK_RETRY_NS 200000L /* as host_api/locks.py */
#define LOCK_FILE_FLAGS (O_RDWR | O_CREAT | O_NOFOLLOW | O_CLOEXEC)
#define LEDGER_LINE 96 /* "pid owner nr b rx tx multi sent_ms\n" fits */
/* The ledger file's size at least, all of it mapped: as host_api/locks.py LEDGER_BYTES */
#define LEDGER_BYTES (CIFEMU_LEDGER_MAX * LEDGER_LINE + 1)
#define SEQ_MASK 0x0C
#define SEQ_FIRST 0x04
#define SEQ_CONT 0x08
#define SEQ_LAST 0x0C
#define NAK_MASK 0x02

long long cifemu_now_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static unsigned long long clamp_ms(unsigned long ms) {
  /* about 24 days at most: a deadline that fits every clock [ours] */
  return ms > 2000000000UL ? 2000000000ULL : (unsigned long long)ms;
}

static void pause_retry(void) {
  struct timespec pause = {0, FLOCK_RETRY_NS};
  nanosleep(&pause, NULL);
}

int cifemu_chanlock_open(cifemu_chanlock *lock, const char *path) {
  lock->fd = path == NULL ? CIFEMU_CHANLOCK_THREAD : open(path, LOCK_FILE_FLAGS, 0660);
  if (lock->fd == -1) return -1;
  pthread_mutex_init(&lock->mutex, NULL);
  return 0;
}

void cifemu_chanlock_close(cifemu_chanlock *lock) {
  if (lock->fd >= 0) close(lock->fd);
  if (lock->fd != -1) pthread_mutex_destroy(&lock->mutex);
  lock->fd = -1;
}

int cifemu_chanlock_reopen(cifemu_chanlock *lock, const char *path) {
  int fd;
  if (lock->fd == -1) return 0;
  /* The parent's threads do not exist here: a mutex one of them held would stay locked. */
  pthread_mutex_init(&lock->mutex, NULL);
  if (lock->fd == CIFEMU_CHANLOCK_THREAD) return 0;
  fd = open(path, LOCK_FILE_FLAGS, 0660);
  if (fd < 0) return -1;
  if (fd == lock->fd) return 0;
  /* one thread after fork: nothing can exec between dup2 and FD_CLOEXEC */
  if (dup2(fd, lock->fd) < 0 || fcntl(lock->fd, F_SETFD, FD_CLOEXEC) != 0) {
    close(fd);
    return -1;
  }
  close(fd);
  return 0;
}

/* The flock, tried until deadline_ns while the caller holds the mutex: 1 taken, else 0. */
static int flock_until(int fd, long long deadline_ns) {
  for (;;) {
    if (flock(fd, LOCK_EX | LOCK_NB) == 0) return 1;
    if ((errno != EWOULDBLOCK && errno != EINTR) || cifemu_now_ns() >= deadline_ns) return 0;
    pause_retry();
  }
}

int cifemu_chanlock_acquire(cifemu_chanlock *lock, unsigned long timeout_ms) {
  unsigned long long ms = clamp_ms(timeout_ms);
  long long deadline;
  if (pthread_mutex_trylock(&lock->mutex) == 0) { /* the uncontended case, without clocks */
    if (lock->fd == CIFEMU_CHANLOCK_THREAD || flock(lock->fd, LOCK_EX | LOCK_NB) == 0) return 1;
    deadline = cifemu_now_ns() + (long long)ms * 1000000LL;
  } else {
    struct timespec until;
    if (ms == 0) return 0;
    deadline = cifemu_now_ns() + (long long)ms * 1000000LL;
    clock_gettime(CLOCK_REALTIME, &until);
    until.tv_sec += (time_t)(ms / 1000);
    until.tv_nsec += (long)(ms % 1000) * 1000000L;
    if (until.tv_nsec >= 1000000000L) {
      until.tv_sec += 1;
      until.tv_nsec -= 1000000000L;
    }
    if (pthread_mutex_timedlock(&lock->mutex, &until) != 0) return 0;
  }
  if (lock->fd == CIFEMU_CHANLOCK_THREAD) return 1;
  /* The mutex stays held while the flock is awaited: the flock is the open file
     description's, so a thread without the mutex would get it too. */
  if (flock_until(lock->fd, deadline)) return 1;
  pthread_mutex_unlock(&lock->mutex);
  return 0;
}

void cifemu_chanlock_release(cifemu_chanlock *lock) {
  if (lock->fd != CIFEMU_CHANLOCK_THREAD) flock(lock->fd, LOCK_UN);
  pthread_mutex_unlock(&lock->mutex);
}

/* ---- the transaction lock and its ledger ----------------------------------------------- */

static long long now_ms(void) { return cifemu_now_ns() / 1000000LL; }

/* The ledger as the file holds it: the stale requests, then this process's, ended by a
   NUL [ours]. The file is not truncated: whatever follows the NUL is left from a longer
   ledger, and every reader stops there (dpm/ledger.py); an empty ledger is not written
   again. Written through the map, without a system call (issue 22), when the change
   empties it (one byte) or appends lines (a request sent, on every round trip): the new
   lines and their NUL after their first byte, then that byte over the old NUL, so a host
   killed meanwhile leaves the ledger as it was or whole. Any other change is one pwrite,
   which a killed host made whole or not at all. */
static void ledger_store(cifemu_txn *txn) {
  char text[CIFEMU_LEDGER_MAX * LEDGER_LINE + 1];
  size_t used = 0;
  unsigned i;
  for (i = 0; i < txn->n_stale + txn->n_own; i++) {
    const cifemu_request *r = i < txn->n_stale ? &txn->stale[i] : &txn->own[i - txn->n_stale];
    int n = snprintf(text + used, sizeof text - 1 - used, "%ld %llu %u %u %u %u %u %lld\n",
                     r->pid, r->owner, r->nr, r->b, r->rx, r->tx, r->multi, r->sent_ms);
    if (n < 0 || (size_t)n >= sizeof text - 1 - used) break;
    used += (size_t)n;
  }
  if (used == 0 && txn->length == 0) return;
  text[used] = '\0';
  if (used == 0) {
    __atomic_store_n(txn->map, (unsigned char)0, __ATOMIC_RELEASE);
    txn->length = 0;
    return;
  }
  if (used > txn->length && memcmp(txn->map, text, txn->length) == 0) {
    memcpy(txn->map + txn->length + 1, text + txn->length + 1, used - txn->length);
    __atomic_store_n(txn->map + txn->length, (unsigned char)text[txn->length], __ATOMIC_RELEASE);
    txn->length = used;
    return;
  }
  if (pwrite(txn->lock.fd, text, used + 1, 0) == (ssize_t)(used + 1)) txn->length = used;
}

/* The file's requests as a new holder sees them: another owner's are stale (its sender
   died, or gave up waiting and let the lock go), this process's own ones are given up.
   Malformed lines and requests older than CIFEMU_STALE_MS (or from the future: another
   boot's clock) are dropped. */
static void ledger_load(cifemu_txn *txn) {
  char text[LEDGER_BYTES], *line, *next;
  size_t got = strnlen((const char *)txn->map, sizeof text - 1); /* read through the map */
  long long now = now_ms();
  unsigned dropped = 0;
  txn->n_stale = txn->n_own = 0;
  memcpy(text, txn->map, got);
  text[got] = '\0';
  txn->length = got;
  if (got == sizeof text - 1) dropped++; /* no NUL: a file someone else wrote */
  for (line = text; line != NULL && *line != '\0'; line = next) {
    cifemu_request r;
    unsigned nr, b, rx, tx, multi;
    next = strchr(line, '\n');
    if (next != NULL) *next++ = '\0';
    if (sscanf(line, "%ld %llu %u %u %u %u %u %lld", &r.pid, &r.owner, &nr, &b, &rx, &tx,
               &multi, &r.sent_ms) != 8 ||
        nr > 255 || b > 255 || rx > 255 || tx > 255 || multi > 2 || r.sent_ms > now ||
        now - r.sent_ms > CIFEMU_STALE_MS || txn->n_stale + txn->n_own >= CIFEMU_LEDGER_MAX) {
      dropped++;
      continue;
    }
    r.nr = (unsigned char)nr;
    r.b = (unsigned char)b;
    r.rx = (unsigned char)rx;
    r.tx = (unsigned char)tx;
    r.multi = (unsigned char)multi;
    r.given_up = 1;
    if (r.owner == txn->owner) txn->own[txn->n_own++] = r;
    else txn->stale[txn->n_stale++] = r;
  }
  if (dropped) ledger_store(txn);
}

/* A number no other process (nor this one's other boards, nor a forked child) has. */
static unsigned long long new_owner(const cifemu_txn *txn) {
  unsigned long long x = (unsigned long long)cifemu_now_ns() ^
                         ((unsigned long long)getpid() << 40) ^ (unsigned long long)(size_t)txn;
  x ^= x >> 33; /* splitmix64's finaliser: the numbers spread over all 64 bits */
  x *= 0xff51afd7ed558ccdULL;
  x ^= x >> 33;
  return x;
}

static void txn_reset(cifemu_txn *txn) {
  txn->owner = new_owner(txn);
  txn->pid = (long)getpid();
  txn->held = 0;
  txn->users = txn->n_own = txn->n_stale = 0;
  txn->length = 0;
}

/* [ours] The ledger file mapped, grown to LEDGER_BYTES first when shorter (zeros: the
   ledger's end to every reader): read and written without a pread and two pwrite per
   mailbox round trip (issue 22), as a Python host does. 0, else -1. */
static int ledger_map(cifemu_txn *txn) {
  struct stat st;
  void *map;
  if (fstat(txn->lock.fd, &st) != 0 ||
      (st.st_size < LEDGER_BYTES && ftruncate(txn->lock.fd, LEDGER_BYTES) != 0))
    return -1;
  map = mmap(NULL, LEDGER_BYTES, PROT_READ | PROT_WRITE, MAP_SHARED, txn->lock.fd, 0);
  if (map == MAP_FAILED) return -1;
  txn->map = (unsigned char *)map;
  return 0;
}

static void ledger_unmap(cifemu_txn *txn) {
  if (txn->map != NULL) munmap(txn->map, LEDGER_BYTES);
  txn->map = NULL;
}

int cifemu_txn_open(cifemu_txn *txn, const char *path) {
  txn_reset(txn);
  txn->map = NULL;
  if (cifemu_chanlock_open(&txn->lock, path) != 0) return -1;
  return ledger_map(txn);
}

void cifemu_txn_close(cifemu_txn *txn) {
  ledger_unmap(txn);
  cifemu_chanlock_close(&txn->lock);
}

int cifemu_txn_reopen(cifemu_txn *txn, const char *path) {
  txn_reset(txn);
  if (txn->lock.fd < 0) return 0;
  if (cifemu_chanlock_reopen(&txn->lock, path) != 0) return -1;
  ledger_unmap(txn); /* the map of the file now at the path, as the flock's */
  return ledger_map(txn);
}

int cifemu_txn_enter(cifemu_txn *txn, unsigned long timeout_ms) {
  long long deadline = cifemu_now_ns() + (long long)clamp_ms(timeout_ms) * 1000000LL;
  int asked = 0;
  /* The mutex is held for one attempt at a time, so that a thread with a short time-out
     is never kept waiting by one with a long time-out. */
  for (;;) {
    int failed = 0;
    pthread_mutex_lock(&txn->lock.mutex);
    if (!txn->held) {
      if (flock(txn->lock.fd, LOCK_EX | LOCK_NB) == 0) {
        txn->held = 1;
        ledger_load(txn);
      } else {
        failed = errno != EWOULDBLOCK && errno != EINTR;
      }
    }
    if (txn->held) {
      txn->users++;
      pthread_mutex_unlock(&txn->lock.mutex);
      return 1;
    }
    pthread_mutex_unlock(&txn->lock.mutex);
    if (failed || cifemu_now_ns() >= deadline) return 0;
    /* [ours] Another process has it: waiting is futile when it keeps the lock for its
       life (the CiA 309 gateway), so the caller hears at once. Asked once per call. */
    if (!asked) {
      asked = 1;
      if (cifemu_held_for_life(txn->lock.fd)) return 0;
    }
    pause_retry();
  }
}

/* The caller holds the mutex. */
static void release_if_idle(cifemu_txn *txn) {
  unsigned i;
  if (!txn->held || txn->users > 0) return;
  for (i = 0; i < txn->n_own; i++)
    if (!txn->own[i].given_up) return;
  flock(txn->lock.fd, LOCK_UN);
  txn->held = 0;
  txn->n_own = txn->n_stale = 0; /* the file keeps them for the next holder */
}

void cifemu_txn_leave(cifemu_txn *txn) {
  pthread_mutex_lock(&txn->lock.mutex);
  if (txn->users > 0) txn->users--;
  release_if_idle(txn);
  pthread_mutex_unlock(&txn->lock.mutex);
}

/* A request that continues a sequence (e CONT or LAST: the load function's transfers) shows
   that the first request of that command, answered with a part marked FIRST, was no long
   upload: its answer is in, it awaits no more. The caller holds the mutex. */
static void drop_sequence_start(cifemu_txn *txn, const cifemu_request *next) {
  unsigned i = 0;
  while (i < txn->n_own) {
    const cifemu_request *r = &txn->own[i];
    if (r->multi == 2 && r->b == next->b && r->rx == next->rx && r->tx == next->tx) {
      memmove(txn->own + i, txn->own + i + 1, (txn->n_own - i - 1) * sizeof *r);
      txn->n_own--;
    } else {
      i++;
    }
  }
}

void cifemu_txn_sent(cifemu_txn *txn, const unsigned char *header) {
  cifemu_request r;
  /* answered only when it fails: none is awaited, and an answer awaited that never came
     would keep every other host off the board until a get of this one timed out */
  if ((header[7] & NAK_MASK) || (header[0] == UNANSWERED_RX && header[6] == UNANSWERED_B))
    return;
  r.pid = txn->pid;
  r.owner = txn->owner;
  r.rx = header[0];
  r.tx = header[1];
  r.nr = header[3];
  r.b = header[6];
  r.multi = (header[7] & SEQ_MASK) == SEQ_FIRST;
  r.given_up = 0;
  r.sent_ms = now_ms();
  pthread_mutex_lock(&txn->lock.mutex);
  if ((header[7] & SEQ_MASK) == SEQ_CONT || (header[7] & SEQ_MASK) == SEQ_LAST)
    drop_sequence_start(txn, &r);
  if (txn->n_own + txn->n_stale >= CIFEMU_LEDGER_MAX) { /* the oldest goes */
    if (txn->n_stale > 0) memmove(txn->stale, txn->stale + 1, --txn->n_stale * sizeof r);
    else memmove(txn->own, txn->own + 1, --txn->n_own * sizeof r);
  }
  txn->own[txn->n_own++] = r;
  ledger_store(txn);
  pthread_mutex_unlock(&txn->lock.mutex);
}

/* The request an answer (header) belongs to in list[0..n), or -1. A long upload that had
   its first part is continued only by a part marked CONT or LAST. */
static int find(const cifemu_request *list, unsigned n, const unsigned char *header) {
  unsigned i, sequence = header[7] & SEQ_MASK;
  for (i = 0; i < n; i++)
    if (list[i].nr == header[3] && list[i].b == header[4] && list[i].rx == header[1] &&
        list[i].tx == header[0] &&
        (list[i].multi != 2 || sequence == SEQ_CONT || sequence == SEQ_LAST))
      return (int)i;
  return -1;
}

/* list[i] was answered by header: gone after its last answer; a long upload's part (f 0,
   e FIRST or CONT, to a request sent with e FIRST) has more after it. */
static void answer_request(cifemu_request *list, unsigned *n, int i, const unsigned char *header) {
  unsigned sequence = header[7] & SEQ_MASK;
  if (list[i].multi && header[5] == 0 && (sequence == SEQ_FIRST || sequence == SEQ_CONT)) {
    list[i].multi = 2;
    return;
  }
  memmove(list + i, list + i + 1, (*n - (unsigned)i - 1) * sizeof *list);
  (*n)--;
}

int cifemu_txn_is_stale(cifemu_txn *txn, const unsigned char *header) {
  int stale;
  pthread_mutex_lock(&txn->lock.mutex);
  stale = find(txn->stale, txn->n_stale, header) >= 0;
  pthread_mutex_unlock(&txn->lock.mutex);
  return stale;
}

int cifemu_txn_answered(cifemu_txn *txn, const unsigned char *header) {
  int i, kind = CIFEMU_ANSWER_OTHER;
  pthread_mutex_lock(&txn->lock.mutex);
  /* Stale requests were sent first: the card answers them first. */
  if ((i = find(txn->stale, txn->n_stale, header)) >= 0) {
    kind = CIFEMU_ANSWER_STALE;
    answer_request(txn->stale, &txn->n_stale, i, header);
  } else if ((i = find(txn->own, txn->n_own, header)) >= 0) {
    kind = CIFEMU_ANSWER_OWN;
    answer_request(txn->own, &txn->n_own, i, header);
  }
  if (kind != CIFEMU_ANSWER_OTHER) ledger_store(txn);
  pthread_mutex_unlock(&txn->lock.mutex);
  return kind;
}

void cifemu_txn_give_up(cifemu_txn *txn) {
  unsigned i;
  pthread_mutex_lock(&txn->lock.mutex);
  for (i = 0; i < txn->n_own; i++) txn->own[i].given_up = 1;
  pthread_mutex_unlock(&txn->lock.mutex);
}
