/*
 * chanlock.h - the locks hosts share on one board, with Python hosts (host_api/locks.py).
 *
 * A channel lock: a thread mutex serialises this process's threads; an flock on
 * <dir>/board<N>.<channel>.lock serialises processes, C and Python alike. The flock
 * belongs to the open file description, which every thread shares: a thread takes the
 * flock only while it holds the mutex, so two threads of one process are never both
 * inside. A caller waits for the channel up to its own timeout, in all; the driver then
 * answers -4.
 *
 * [ours] A channel lock opened without a path is a thread lock only (the put and get
 * channels): every put and get is made inside the transaction lock, which one process at
 * a time holds, so an flock of their own excluded nobody more and cost four system calls
 * per mailbox round trip (issue 22), as the Python driver's put and get channels.
 *
 * The transaction lock [ours]: an flock on <dir>/board<N>.transaction.lock that a host
 * process holds from a DevPutMessage until that request is answered, so that another
 * host never reads its answer. The file is the lock's ledger: one line per request whose
 * answer is awaited ("pid owner nr b rx tx multi sent_ms", owner: a random number per
 * process and board). The kernel frees the flock of a host that dies; the next holder
 * finds the dead host's requests in the ledger and discards their answers when they
 * come. A host whose DevGetMessage timed out gives the lock up when no other call of it
 * is inside; its late answers are its own while it holds the lock again, and another
 * host's to discard once that host took it (docs/libcif.md).
 */
#ifndef CIFEMU_CHANLOCK_H
#define CIFEMU_CHANLOCK_H

#include <pthread.h>

#define CIFEMU_CHANLOCK_THREAD (-2) /* fd of a thread lock only (opened without a path) */

typedef struct cifemu_chanlock {
  pthread_mutex_t mutex;
  int fd; /* -1 while not open, CIFEMU_CHANLOCK_THREAD: no file */
} cifemu_chanlock;

/* Opens (O_NOFOLLOW: a planted link is refused) or creates the lock file: 0, else -1.
   path NULL: a thread lock only, no file. */
int cifemu_chanlock_open(cifemu_chanlock *lock, const char *path);
void cifemu_chanlock_close(cifemu_chanlock *lock);
/* In a forked child: a lock file description of its own at the same descriptor number
   (the parent's flocks stay the parent's) and a fresh mutex. 0, else -1. */
int cifemu_chanlock_reopen(cifemu_chanlock *lock, const char *path);
/* 1 when taken within timeout_ms (0: only if free now), else 0. */
int cifemu_chanlock_acquire(cifemu_chanlock *lock, unsigned long timeout_ms);
void cifemu_chanlock_release(cifemu_chanlock *lock);

long long cifemu_now_ns(void); /* CLOCK_MONOTONIC */

/* ---- the transaction lock and its ledger [ours] ---- */

#define CIFEMU_LEDGER_MAX 128
/* A dead host's request is forgotten this long after it was sent: a card answers within
   it or never (the driver's longest wait is DevDownload's 15 s). */
#define CIFEMU_STALE_MS 30000LL

typedef struct cifemu_request {
  long pid;
  unsigned long long owner;
  unsigned char nr, b, rx, tx;
  unsigned char multi; /* 0: one answer ends it; sent with e FIRST, a long upload's parts
                          may follow: 1 before its first part, 2 after it */
  unsigned char given_up; /* in memory: a get timed out waiting for it */
  long long sent_ms;   /* CLOCK_MONOTONIC */
} cifemu_request;

typedef struct cifemu_txn {
  cifemu_chanlock lock;  /* fd: the flock; mutex: guards the fields below, never held long */
  unsigned long long owner; /* this process's number in the ledger (new after a fork) */
  long pid;              /* getpid() at open and after a fork: a ledger line's first field,
                            without a system call per request (glibc does not cache it) */
  int held;              /* this process holds the flock */
  unsigned users;        /* calls and sessions (DevDownload) inside */
  unsigned n_own, n_stale;
  size_t length; /* the ledger's length up to its end (a NUL or the file's end) as this
                    process last read or wrote it while holding the flock */
  unsigned char *map; /* the ledger file mapped (chanlock.c ledger_map); NULL: not open */
  cifemu_request own[CIFEMU_LEDGER_MAX];   /* this process's requests awaiting answers */
  cifemu_request stale[CIFEMU_LEDGER_MAX]; /* other processes' requests: discard */
} cifemu_txn;

/* What an answer read from the host mailbox was. */
enum { CIFEMU_ANSWER_OTHER = 0, CIFEMU_ANSWER_OWN = 1, CIFEMU_ANSWER_STALE = 2 };

int cifemu_txn_open(cifemu_txn *txn, const char *path);
void cifemu_txn_close(cifemu_txn *txn);
/* In a forked child: its own flock, an empty ledger in memory (the file is the parent's). */
int cifemu_txn_reopen(cifemu_txn *txn, const char *path);
/* A call starts: the process holds the lock within timeout_ms (1, counted), else 0; 0 at
   once when the process holding it is a CiA 309 gateway, which keeps it while it runs
   (holder.h). */
int cifemu_txn_enter(cifemu_txn *txn, unsigned long timeout_ms);
/* The call ends: the lock is given back when no call is inside and no answer is awaited
   (answers a timed-out get gave up on do not keep it). */
void cifemu_txn_leave(cifemu_txn *txn);
/* Before the request (MSG_STRUC's first 8 bytes) goes to the card: recorded in the ledger,
   unless the card answers it only when it fails (msg.e NAK, or UNANSWERED_RX/_B in dpm.h). */
void cifemu_txn_sent(cifemu_txn *txn, const unsigned char *header);
/* Whether the answer in the mailbox (its first 8 bytes) is one to discard. */
int cifemu_txn_is_stale(cifemu_txn *txn, const unsigned char *header);
/* After the answer (its first 8 bytes) was taken from the mailbox: whose it was. A stale
   one is the caller's to discard. */
int cifemu_txn_answered(cifemu_txn *txn, const unsigned char *header);
/* A get timed out: the answers awaited do not keep the lock any more. */
void cifemu_txn_give_up(cifemu_txn *txn);

#endif
