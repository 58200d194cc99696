/*
 * hosts.c - C hosts that share a card with threads, other processes, killed hosts and
 * forks (tests/test_libcif_hosts.py). Every request is tagged: a COM_Shared_Memory read
 * at data_adr TAG with msg.nr TAG % 255 + 1, which the card's answer echoes, so every
 * answer read can be attributed to the request that asked for it.
 *
 * Usage: CIF_DPM_DIR=<dir> hosts MODE ARGS
 *   threads GETTERS COUNT   one thread puts COUNT requests while GETTERS threads read the
 *                           answers, and another open file description of the
 *                           transaction lock takes its flock again and again (another
 *                           host; the put and get channels are thread locks inside it);
 *                           every answer must be read exactly once
 *   pairs THREADS COUNT BASE  THREADS threads each pair COUNT raw put/get calls (tags BASE
 *                           + thread * COUNT + i); the process must read each of its
 *                           answers exactly once, and no other host's
 *   hang TAG                put one request, say "sent", wait to be killed
 *   late TAG                put one request to a frozen card, get it with a 100 ms time-out
 *                           (-18), say "timed out", wait for a line on stdin (the card
 *                           thaws), then pair 50 requests TAG+1 ...: all this host's own
 *   fork COUNT              DevInitBoard, fork; parent (tags 0 ...) and child (tags 1000
 *                           ...) each pair COUNT requests at once: each reads its own
 *   badlock                 DevInitBoard when a lock file cannot be opened: -31, and
 *                           descriptor 0 still open
 *   exitwait TAG TIMEOUT    a daemon's shutdown: thread A waits in DevGetMessage (TIMEOUT
 *                           ms); once it is inside, thread B calls DevExitBoard and
 *                           DevCloseDriver, and a call after them gets -32. With TAG > 0
 *                           the request TAG was put first to a frozen card: B then says
 *                           "closed" and waits for a line on stdin (the card thaws), and A
 *                           must read that answer; with TAG 0 A ends with -18. The board
 *                           is unmapped after A's call, and opens and works again.
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "cif_user.h"
#include "com_user.h"
#include "rcs_user.h"

#define MAX_TAGS 4096
#define TIMEOUT_MS 5000L

static unsigned seen[MAX_TAGS]; /* answers read per tag, updated atomically */
static unsigned answered, failures, done;

static void fail(const char *what, unsigned tag, int code) {
  fprintf(stderr, "hosts: %s (tag %u, code %d)\n", what, tag, code);
  __atomic_fetch_add(&failures, 1u, __ATOMIC_RELAXED);
}

static short put_tagged(unsigned tag) {
  RCS_MESSAGETELEGRAM_10 msg;
  memset(&msg, 0, sizeof msg);
  msg.rx = COM_TASK_PLC;
  msg.tx = COM_TASK_USER;
  msg.ln = RCS_TELEGRAMHEADER_LEN;
  msg.nr = (unsigned char)(tag % 255 + 1);
  msg.b = COM_Shared_Memory;
  msg.data_area = COM_SHM_AREA_RECEIVE;
  msg.data_adr = (unsigned short)tag;
  msg.data_cnt = 2;
  msg.data_type = TASK_TDT_UINT8;
  msg.function = TASK_TFC_READ;
  return DevPutMessage(0, (MSG_STRUC *)&msg, TIMEOUT_MS);
}

/* One answer: its tag, or -1 with the code (or a malformed answer) reported. */
static long get_tagged(unsigned long timeout, short *rc) {
  RCS_MESSAGETELEGRAM_10 answer;
  *rc = DevGetMessage(0, sizeof answer, (MSG_STRUC *)&answer, timeout);
  if (*rc != DRV_NO_ERROR) return -1;
  if (answer.a != COM_Shared_Memory || answer.f != 0 || answer.data_adr >= MAX_TAGS ||
      answer.nr != answer.data_adr % 255 + 1) {
    fail("an answer that is no tagged read's", answer.data_adr, answer.a);
    return -1;
  }
  __atomic_fetch_add(&seen[answer.data_adr], 1u, __ATOMIC_RELAXED);
  __atomic_fetch_add(&answered, 1u, __ATOMIC_RELAXED);
  return answer.data_adr;
}

static int open_board(void) {
  short rc;
  if ((rc = DevOpenDriver()) != DRV_NO_ERROR || (rc = DevInitBoard(0)) != DRV_NO_ERROR) {
    fprintf(stderr, "hosts: open: %d\n", rc);
    return -1;
  }
  return 0;
}

/* Every tag of [first, first + count) read once, no other tag: 0, else failures. */
static unsigned check_tags(unsigned first, unsigned count) {
  unsigned tag, bad = 0;
  for (tag = 0; tag < MAX_TAGS; tag++) {
    unsigned want = tag >= first && tag < first + count;
    if (seen[tag] != want) {
      fprintf(stderr, "hosts: tag %u read %u times, expected %u\n", tag, seen[tag], want);
      bad++;
    }
  }
  return bad + failures;
}

/* ---- threads ---------------------------------------------------------------------- */

static unsigned total;

static void *getter(void *unused) {
  short rc;
  (void)unused;
  while (__atomic_load_n(&answered, __ATOMIC_RELAXED) < total &&
         !__atomic_load_n(&done, __ATOMIC_RELAXED)) {
    if (get_tagged(200, &rc) < 0 && rc != DRV_DEV_GET_TIMEOUT && rc != DRV_NO_ERROR &&
        rc != DRV_CMD_ACTIVE)
      fail("DevGetMessage", 0, rc);
  }
  return NULL;
}

/* Another host on the same board: the transaction lock's flock taken through a description
   of its own, whenever this host's calls let it go (no answer awaited). */
static void *contender(void *unused) {
  char path[4096];
  struct timespec hold = {0, 300000};
  int fd;
  (void)unused;
  snprintf(path, sizeof path, "%s/board0.transaction.lock", getenv("CIF_DPM_DIR"));
  fd = open(path, O_RDWR | O_CLOEXEC);
  if (fd < 0) {
    fail("contender: open", 0, errno);
    return NULL;
  }
  while (!__atomic_load_n(&done, __ATOMIC_RELAXED)) {
    if (flock(fd, LOCK_EX | LOCK_NB) == 0) {
      nanosleep(&hold, NULL);
      flock(fd, LOCK_UN);
    }
    nanosleep(&hold, NULL);
  }
  close(fd);
  return NULL;
}

static int threads(unsigned getters, unsigned count) {
  pthread_t got[16], other;
  unsigned i;
  short rc;
  if (getters > 16 || count > MAX_TAGS || open_board() != 0) return 1;
  total = count;
  pthread_create(&other, NULL, contender, NULL);
  for (i = 0; i < getters; i++) pthread_create(&got[i], NULL, getter, NULL);
  for (i = 0; i < count; i++)
    if ((rc = put_tagged(i)) != DRV_NO_ERROR) fail("DevPutMessage", i, rc);
  {
    struct timespec start, now;
    struct timespec step = {0, 1000000};
    clock_gettime(CLOCK_MONOTONIC, &start);
    do { /* the getters end when every answer is in; a lost one ends them at 10 s */
      nanosleep(&step, NULL);
      clock_gettime(CLOCK_MONOTONIC, &now);
    } while (__atomic_load_n(&answered, __ATOMIC_RELAXED) < count && now.tv_sec - start.tv_sec < 10);
  }
  __atomic_store_n(&done, 1u, __ATOMIC_RELAXED);
  for (i = 0; i < getters; i++) pthread_join(got[i], NULL);
  pthread_join(other, NULL);
  DevCloseDriver();
  if (check_tags(0, count) != 0) return 1;
  printf("threads: %u answers, each read once\n", count);
  return 0;
}

/* ---- pairs ------------------------------------------------------------------------ */

typedef struct pairs_job {
  unsigned first, count;
} pairs_job;

static void pair_range(unsigned first, unsigned count) {
  unsigned i;
  short rc;
  for (i = 0; i < count; i++) {
    if ((rc = put_tagged(first + i)) != DRV_NO_ERROR) {
      fail("DevPutMessage", first + i, rc);
      continue;
    }
    if (get_tagged(TIMEOUT_MS, &rc) < 0 && rc != DRV_NO_ERROR) fail("DevGetMessage", first + i, rc);
  }
}

static void *pairs_thread(void *arg) {
  const pairs_job *job = (const pairs_job *)arg;
  pair_range(job->first, job->count);
  return NULL;
}

static int pairs(unsigned n, unsigned count, unsigned base) {
  pthread_t thread[16];
  pairs_job job[16];
  unsigned i;
  if (n == 0 || n > 16 || base + n * count > MAX_TAGS || open_board() != 0) return 1;
  for (i = 0; i < n; i++) {
    job[i].first = base + i * count;
    job[i].count = count;
    pthread_create(&thread[i], NULL, pairs_thread, &job[i]);
  }
  for (i = 0; i < n; i++) pthread_join(thread[i], NULL);
  DevCloseDriver();
  if (check_tags(base, n * count) != 0) return 1;
  printf("pairs: %u answers, each this host's own, read once\n", n * count);
  return 0;
}

/* ---- killed, late, forked ------------------------------------------------------------ */

static int hang(unsigned tag) {
  short rc;
  if (open_board() != 0) return 1;
  if ((rc = put_tagged(tag)) != DRV_NO_ERROR) {
    fail("DevPutMessage", tag, rc);
    return 1;
  }
  printf("sent\n");
  fflush(stdout);
  for (;;) pause();
}

static int late(unsigned tag) {
  char line[16];
  short rc;
  if (open_board() != 0) return 1;
  if ((rc = put_tagged(tag)) != DRV_NO_ERROR) {
    fail("DevPutMessage", tag, rc);
    return 1;
  }
  if (get_tagged(100, &rc) >= 0 || rc != DRV_DEV_GET_TIMEOUT) {
    fail("DevGetMessage of a frozen card", tag, rc);
    return 1;
  }
  printf("timed out\n");
  fflush(stdout);
  if (fgets(line, sizeof line, stdin) == NULL) return 1;
  pair_range(tag + 1, 50);
  DevCloseDriver();
  if (check_tags(tag + 1, 50) != 0) return 1;
  printf("late: 50 answers, each this host's own; the late one discarded\n");
  return 0;
}

static int forked(unsigned count) {
  pid_t child;
  int status;
  if (count > 1000 || open_board() != 0) return 1;
  fflush(stdout);
  child = fork();
  if (child < 0) return 1;
  if (child == 0) {
    pair_range(1000, count);
    DevCloseDriver();
    _exit(check_tags(1000, count) != 0);
  }
  pair_range(0, count);
  DevCloseDriver();
  if (waitpid(child, &status, 0) != child || !WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    fprintf(stderr, "hosts: the child failed\n");
    return 1;
  }
  if (check_tags(0, count) != 0) return 1;
  printf("fork: parent and child each read their own %u answers\n", count);
  return 0;
}

static int badlock(void) {
  struct stat before, after;
  short rc;
  if (fstat(0, &before) != 0) return 1;
  if ((rc = DevOpenDriver()) != DRV_NO_ERROR) return 1;
  rc = DevInitBoard(0);
  DevCloseDriver();
  if (rc != DRV_USR_INIT_DRV_ERROR) {
    fprintf(stderr, "hosts: DevInitBoard %d, expected -31\n", rc);
    return 1;
  }
  if (fstat(0, &after) != 0 || after.st_ino != before.st_ino || after.st_dev != before.st_dev) {
    fprintf(stderr, "hosts: descriptor 0 was closed\n");
    return 1;
  }
  printf("badlock: -31, descriptor 0 open\n");
  return 0;
}

/* ---- exitwait -------------------------------------------------------------------------- */

static unsigned long waiter_timeout;
static short waiter_rc;
static long waiter_tag;
static unsigned waiter_done;

static long waiter_tid;

static void *waiter(void *unused) {
  (void)unused;
  __atomic_store_n(&waiter_tid, (long)syscall(SYS_gettid), __ATOMIC_RELEASE);
  waiter_tag = get_tagged(waiter_timeout, &waiter_rc);
  __atomic_store_n(&waiter_done, 1u, __ATOMIC_RELEASE);
  return NULL;
}

/* Whether the waiter sleeps in its DevGetMessage's wait: on the bell, in poll (syscall 7,
   or ppoll, 271, as /proc/self/task/TID/syscall says). The get channel is a thread lock
   inside the transaction lock, which a put before holds already: no file lock tells. */
static int inside_get(void) {
  char path[64];
  long tid = __atomic_load_n(&waiter_tid, __ATOMIC_ACQUIRE), call = -1;
  FILE *f;
  if (tid == 0) return 0;
  snprintf(path, sizeof path, "/proc/self/task/%ld/syscall", tid);
  if ((f = fopen(path, "r")) == NULL) return 0;
  if (fscanf(f, "%ld", &call) != 1) call = -1;
  fclose(f);
  return call == 7 || call == 271;
}

/* Whether board 0's image is mapped into this process. */
static int image_mapped(void) {
  char line[4096];
  int found = 0;
  FILE *maps = fopen("/proc/self/maps", "r");
  if (maps == NULL) return -1;
  while (fgets(line, sizeof line, maps) != NULL)
    if (strstr(line, "/board0.dpm") != NULL) found = 1;
  fclose(maps);
  return found;
}

static int exitwait(unsigned tag, unsigned long timeout) {
  struct timespec start, now, step = {0, 1000000};
  pthread_t thread;
  char line[16];
  short rc;
  int inside = 0, bad = 0;
  if (tag >= MAX_TAGS || open_board() != 0) return 1;
  if (tag > 0 && (rc = put_tagged(tag)) != DRV_NO_ERROR) {
    fail("DevPutMessage", tag, rc);
    return 1;
  }
  waiter_timeout = timeout;
  pthread_create(&thread, NULL, waiter, NULL);
  clock_gettime(CLOCK_MONOTONIC, &start);
  do {
    inside = inside_get();
    if (!inside) nanosleep(&step, NULL);
    clock_gettime(CLOCK_MONOTONIC, &now);
  } while (!inside && now.tv_sec - start.tv_sec < 10);
  if (!inside) {
    fprintf(stderr, "hosts: the waiter never entered DevGetMessage\n");
    return 1;
  }
  if ((rc = DevExitBoard(0)) != DRV_NO_ERROR) bad += fprintf(stderr, "hosts: DevExitBoard %d\n", rc) > 0;
  if ((rc = put_tagged(tag + 1)) != DRV_USR_NOT_INITIALIZED)
    bad += fprintf(stderr, "hosts: DevPutMessage after DevExitBoard %d, expected -32\n", rc) > 0;
  if ((rc = DevCloseDriver()) != DRV_NO_ERROR)
    bad += fprintf(stderr, "hosts: DevCloseDriver %d\n", rc) > 0;
  if (__atomic_load_n(&waiter_done, __ATOMIC_ACQUIRE))
    bad += fprintf(stderr, "hosts: the waiter's call ended at DevExitBoard\n") > 0;
  if (tag > 0) {
    printf("closed\n");
    fflush(stdout);
    if (fgets(line, sizeof line, stdin) == NULL) return 1;
  }
  pthread_join(thread, NULL);
  if (tag > 0 && (waiter_rc != DRV_NO_ERROR || waiter_tag != (long)tag))
    bad += fprintf(stderr, "hosts: the waiter got %d (tag %ld), expected its answer %u\n",
                   waiter_rc, waiter_tag, tag) > 0;
  if (tag == 0 && waiter_rc != DRV_DEV_GET_TIMEOUT)
    bad += fprintf(stderr, "hosts: the waiter got %d, expected -18\n", waiter_rc) > 0;
  if (image_mapped() != 0) bad += fprintf(stderr, "hosts: still mapped after the last call\n") > 0;
  memset(seen, 0, sizeof seen);
  if (open_board() != 0) return 1;
  pair_range(tag + 2, 1);
  DevCloseDriver();
  if (bad || check_tags(tag + 2, 1) != 0) return 1;
  printf("exitwait: the waiter ended with %d, the board closed under it, and opens again\n",
         waiter_rc);
  return 0;
}

int main(int argc, char **argv) {
  unsigned a = argc > 2 ? (unsigned)strtoul(argv[2], NULL, 0) : 0;
  unsigned b = argc > 3 ? (unsigned)strtoul(argv[3], NULL, 0) : 0;
  unsigned c = argc > 4 ? (unsigned)strtoul(argv[4], NULL, 0) : 0;
  if (argc >= 4 && strcmp(argv[1], "threads") == 0) return threads(a, b);
  if (argc >= 5 && strcmp(argv[1], "pairs") == 0) return pairs(a, b, c);
  if (argc >= 3 && strcmp(argv[1], "hang") == 0) return hang(a);
  if (argc >= 3 && strcmp(argv[1], "late") == 0) return late(a);
  if (argc >= 3 && strcmp(argv[1], "fork") == 0) return forked(a);
  if (argc >= 2 && strcmp(argv[1], "badlock") == 0) return badlock();
  if (argc >= 4 && strcmp(argv[1], "exitwait") == 0) return exitwait(a, b);
  fprintf(stderr, "usage: hosts threads|pairs|hang|late|fork|badlock|exitwait ARGS\n");
  return 2;
}
