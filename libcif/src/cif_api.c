/*
 * cif_api.c - the CIF device driver API over an emulated card's image (libcif).
 *
 * The behaviour of host_api/driver.py, in C and without Python in the host
 * process: the same return codes in the same order of checks, the same channel
 * locks (so C and Python hosts serialise on one card), the same doorbell with the
 * polling fallback. docs/dpm.md section 4 is the table both follow. What only the C API
 * has (null pointers, DevGetBoardInfoEx, DevSetOpMode, DevGetMBXData,
 * DevReadWriteDPMData, DevExtendedData) is marked [ours] where the real driver's
 * behaviour is not documented.
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/sysmacros.h>
#include <time.h>
#include <unistd.h>

#include "dpm.h"
#include "driver.h"

#define CIF_API __attribute__((visibility("default")))
#define DRIVER_VERSION "cifemu V0.1.0"
#define DEFAULT_DPM_DIR "/dev/shm/cif"
#define SPIN_NS 100000LL          /* watch the flags this long before sleeping on the bell */
#define SPIN_BACKOFF_MAX 6U        /* [ours] host_api/registry.py's: up to 63 waits sleep at once */
#define POLL_INTERVAL_NS 1000000LL /* a waiting host's 1 ms poll, docs/dpm.md section 2 */
#define SPECIAL_CONTROL_WAIT_MS 100UL
#define POLLS_BEFORE_YIELD 8       /* [ours] host_api/registry.py's, docs/dpm.md section 2 */
#define POLL_WINDOW_NS 1000000LL
#define STATE_FLAG_UNKNOWN 0xFF

CIF_API int hDevDrv = -1;

static pthread_mutex_t driver_lock = PTHREAD_MUTEX_INITIALIZER;
/* The board table's lock: boards[], each board's users and closing, closing_boards.
   Taken for a moment by every call; under driver_lock where both are held. */
static pthread_mutex_t table_lock = PTHREAD_MUTEX_INITIALIZER;
static cifemu_board *closing_boards; /* closed, still mapped for the calls inside */
static unsigned int open_count;
static char directory[PATH_MAX];
static cifemu_board *boards[MAX_DEV_BOARDS];
static cifemu_counters counters[MAX_DEV_BOARDS];
/* DRIVERINFO per board number: kept from DevExitBoard to the next DevInitBoard while
   the driver stays open, as the Python driver keeps them. */

/* DRIVERINFO's counters are updated by every thread of the host: atomically. */
static void count(unsigned int *counter) { __atomic_fetch_add(counter, 1u, __ATOMIC_RELAXED); }

/* ---- flags ---------------------------------------------------------------- */

static unsigned char flag_get(const cifemu_board *b, unsigned offset) {
  return __atomic_load_n(b->mm + offset, __ATOMIC_ACQUIRE);
}
static unsigned char host_flags(const cifemu_board *b) { return flag_get(b, OFS_HOST_FLAGS); }
static unsigned char dev_flags(const cifemu_board *b) { return flag_get(b, OFS_DEV_FLAGS); }
static int ready(const cifemu_board *b) { return (host_flags(b) & FL_READY) != 0; }
static int pending(const cifemu_board *b, unsigned char channel) {
  return ((host_flags(b) ^ dev_flags(b)) & channel) != 0;
}

/* Change DevFlags by one atomic read-modify-write, then ring the device. [ours] Every
   host process writes DevFlags, Python hosts too: a compare-and-swap on the byte (as
   host_api/_devflags.c) loses no host's toggle, without the flock round on
   board<N>.flags.lock (four system calls per mailbox round trip) that guarded it before
   issue 22. seq_cst: what the host wrote before (a message in DevMbx) is seen first. */
static void change_dev_flags(cifemu_board *b, unsigned char set, unsigned char clear,
                             unsigned char toggle, int ring) {
  unsigned char *flags = b->mm + OFS_DEV_FLAGS;
  unsigned char old = __atomic_load_n(flags, __ATOMIC_RELAXED), value;
  do {
    value = (unsigned char)(((old | set) & ~clear & 0xFF) ^ toggle);
  } while (!__atomic_compare_exchange_n(flags, &old, value, 0, __ATOMIC_SEQ_CST,
                                        __ATOMIC_RELAXED));
  if (ring) cifemu_bell_ring(&b->bell);
}

typedef int (*condition_fn)(const cifemu_board *b, int arg);

/* Watch the flags for SPIN_NS from `now`: 1 when the condition came true.
   [ours] A watch the answer outlasted cost its whole CPU time for nothing, and on a busy
   machine it takes that time from the card, whose threads wait for a CPU to answer: the
   next 1, 3, 7 ... (SPIN_BACKOFF_MAX) waits sleep at once, until a watch sees its answer
   or a wait that slept at once ends within SPIN_NS (a watch would have seen it: the
   machine is quiet again; host_api/registry.py, MappedBoard._spin). */
static int spin(cifemu_board *b, condition_fn cond, int arg, long long now) {
  long long spin_end = now + SPIN_NS;
  unsigned misses;
  while (cifemu_now_ns() < spin_end)
    if (cond(b, arg)) {
      __atomic_store_n(&b->spin_misses, 0U, __ATOMIC_RELAXED);
      return 1;
    }
  misses = __atomic_load_n(&b->spin_misses, __ATOMIC_RELAXED) + 1U;
  if (misses > SPIN_BACKOFF_MAX) misses = SPIN_BACKOFF_MAX;
  __atomic_store_n(&b->spin_misses, misses, __ATOMIC_RELAXED);
  __atomic_store_n(&b->spin_skip, (1U << misses) - 1U, __ATOMIC_RELAXED);
  return 0;
}

/* Wait on the bell (polling as a fallback) until the condition or the timeout.
   want_mailbox: ring the device before the first sleep, asking for a ring once the device
   mailbox is free (it rings for a message it took only when asked). */
static int wait_for_ringing(cifemu_board *b, condition_fn cond, int arg,
                            unsigned long timeout_ms, int want_mailbox) {
  long long deadline, now;
  unsigned skip;
  if (cond(b, arg)) return 1;
  if (timeout_ms == 0) return 0;
  if (timeout_ms > 2000000000UL) timeout_ms = 2000000000UL;
  now = cifemu_now_ns();
  deadline = now + (long long)timeout_ms * 1000000LL;
  /* A card answers most requests within tens of microseconds: watching the flags
     that long first saves the sleep and wake-up of the bell. */
  skip = __atomic_load_n(&b->spin_skip, __ATOMIC_RELAXED);
  if (skip > 0)
    __atomic_store_n(&b->spin_skip, skip - 1U, __ATOMIC_RELAXED);
  else if (spin(b, cond, arg, now))
    return 1;
  if (want_mailbox) cifemu_bell_ring_want_mailbox(&b->bell);
  for (;;) {
    long long remaining = deadline - cifemu_now_ns();
    if (remaining <= 0) return cond(b, arg);
    if (cifemu_bell_wait(&b->bell, remaining < POLL_INTERVAL_NS ? remaining : POLL_INTERVAL_NS))
      count(&b->counters->irq);
    if (cond(b, arg)) {
      if (skip > 0 && cifemu_now_ns() - now < SPIN_NS) { /* a watch would have seen it */
        __atomic_store_n(&b->spin_misses, 0U, __ATOMIC_RELAXED);
        __atomic_store_n(&b->spin_skip, 0U, __ATOMIC_RELAXED);
      }
      return 1;
    }
  }
}

static int wait_for(cifemu_board *b, condition_fn cond, int arg, unsigned long timeout_ms) {
  return wait_for_ringing(b, cond, arg, timeout_ms, 0);
}

/* What is left of a call's time-out that started at `start` (CLOCK_MONOTONIC ns). */
static unsigned long remaining_ms(long long start, unsigned long timeout_ms) {
  long long left;
  if (timeout_ms > 2000000000UL) timeout_ms = 2000000000UL;
  left = start + (long long)timeout_ms * 1000000LL - cifemu_now_ns();
  return left > 0 ? (unsigned long)((left + 999999) / 1000000) : 0UL;
}

static int cond_pending(const cifemu_board *b, int channel) {
  return pending(b, (unsigned char)channel);
}
static int cond_free(const cifemu_board *b, int channel) {
  return !pending(b, (unsigned char)channel);
}
static int cond_pd_turn(const cifemu_board *b, int device_controlled) {
  return pending(b, CH_PD) == device_controlled;
}
static int cond_reset_done(const cifemu_board *b, int unused) {
  (void)unused;
  return (dev_flags(b) & (FL_RESET | FL_INIT)) == 0;
}
static int cond_ready(const cifemu_board *b, int unused) {
  (void)unused;
  return ready(b);
}
static int cond_host_bit(const cifemu_board *b, int bit_and_level) {
  int bit = bit_and_level & 0xFF, want = bit_and_level >> 8;
  return ((host_flags(b) & bit) != 0) == want;
}

/* ---- boards --------------------------------------------------------------- */

static void board_close(cifemu_board *b);

/* [ours] The real driver's board lived in the kernel, and a call waiting in it when the
   program closed the board finished on it. So here: a call counts itself in the board
   (users) while it is inside; DevExitBoard takes the board out of the table (later calls
   get -32) and the last call inside unmaps it. No call waits for another. */
cifemu_board *cifemu_board_enter(unsigned short number, short *rc) {
  cifemu_board *b;
  if (number >= MAX_DEV_BOARDS) {
    *rc = DRV_USR_DEV_NUMBER_INVALID;
    return NULL;
  }
  pthread_mutex_lock(&table_lock);
  b = boards[number]; /* none while the driver is closed: DevCloseDriver empties the table */
  if (b != NULL) b->users++;
  pthread_mutex_unlock(&table_lock);
  *rc = b != NULL ? DRV_NO_ERROR : DRV_USR_NOT_INITIALIZED;
  return b;
}

cifemu_board *cifemu_ready_board(unsigned short number, short *rc) {
  cifemu_board *b = cifemu_board_enter(number, rc);
  if (b != NULL && !ready(b)) {
    cifemu_board_leave(b);
    *rc = DRV_DEV_NOT_READY;
    return NULL;
  }
  return b;
}

void cifemu_board_leave(cifemu_board *b) {
  cifemu_board **link;
  int last;
  pthread_mutex_lock(&table_lock);
  last = --b->users == 0 && b->closing;
  if (last) {
    for (link = &closing_boards; *link != b; link = &(*link)->next_closing) {
    }
    *link = b->next_closing;
  }
  pthread_mutex_unlock(&table_lock);
  if (last) board_close(b);
}

/* Takes board `number` out of the table (the caller holds driver_lock): unmapped now when
   no call is inside, else by the last one to leave. 0, or -32 when it was not there. */
static short board_remove(unsigned short number) {
  cifemu_board *b;
  int idle;
  pthread_mutex_lock(&table_lock);
  b = boards[number];
  boards[number] = NULL;
  idle = b != NULL && b->users == 0;
  if (b != NULL && !idle) {
    b->closing = 1;
    b->next_closing = closing_boards;
    closing_boards = b;
  }
  pthread_mutex_unlock(&table_lock);
  if (idle) board_close(b);
  return b != NULL ? DRV_NO_ERROR : DRV_USR_NOT_INITIALIZED;
}

static void image_path(char *out, size_t size, unsigned short number) {
  snprintf(out, size, "%s/board%u.dpm", directory, (unsigned)number);
}

/* [ours] Whether a process holds board `number`'s firmware lock (flock on
 * board<N>.firmware.lock), as host_api.liveness asks: a killed firmware leaves READY set
 * in the image, so only its lock tells. Read from /proc/locks, since a probing flock
 * could make a firmware starting in that instant refuse itself; without /proc, a shared
 * non-blocking flock that fails means a holder. The kernel hands /proc/locks out a page
 * per read, and a lock falls between two pages when locks listed before it go meanwhile
 * (under load, five reads in a row missed): a "not held" is not believed while the pid
 * recorded in the lock file names the process that wrote it, one that runs and started no
 * later than the file's last write (a pid used again belongs to a later process). */
#define START_SLACK_S 0.02 /* as host_api/liveness.py */

/* 1 held (`*holder`: its pid, 0 for one in another pid namespace), 0 not held, -1 no
 * /proc/locks. */
static int lock_table_holds(const char *device, long *holder) {
  char line[256];
  FILE *locks = fopen("/proc/locks", "r");
  int held = 0;
  if (locks == NULL) return -1;
  while (!held && fgets(line, sizeof line, locks) != NULL) {
    char kind[16], pid[24], where[64];
    if (strstr(line, "->") != NULL) continue; /* a waiter, not a holder */
    if (sscanf(line, "%*s %15s %*s %*s %23s %63s", kind, pid, where) == 3 &&
        strcmp(kind, "FLOCK") == 0 && strcmp(where, device) == 0) {
      held = 1;
      *holder = strtol(pid, NULL, 10);
    }
  }
  fclose(locks);
  return held;
}

static double seconds(clockid_t clock) {
  struct timespec t;
  clock_gettime(clock, &t);
  return (double)t.tv_sec + (double)t.tv_nsec / 1e9;
}

/* Whether the pid written in the lock file runs (not a zombie) and started no later than
 * the file's last write (`st`); without /proc, whether it exists. */
/* The pid written in the lock file, 0 when there is none (a clean stop empties it). */
static long recorded_pid(const char *path) {
  char text[32];
  ssize_t n;
  long pid;
  int fd = open(path, O_RDONLY | O_CLOEXEC);
  if (fd < 0) return 0;
  n = read(fd, text, sizeof text - 1);
  close(fd);
  if (n <= 0) return 0;
  text[n] = '\0';
  pid = strtol(text, NULL, 10);
  return pid > 0 ? pid : 0;
}

static int recorded_pid_wrote(const char *path, const struct stat *st) {
  char stat_path[64], proc[1024];
  const char *fields;
  unsigned long long start = 0;
  char state = '?';
  ssize_t n;
  long pid = recorded_pid(path);
  int fd;
  if (pid <= 0) return 0;
  snprintf(stat_path, sizeof stat_path, "/proc/%ld/stat", pid);
  fd = open(stat_path, O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return 0;
    return kill((pid_t)pid, 0) == 0 || errno == EPERM;
  }
  n = read(fd, proc, sizeof proc - 1);
  close(fd);
  if (n <= 0) return 0;
  proc[n] = '\0';
  fields = strrchr(proc, ')');
  if (fields == NULL ||
      sscanf(fields + 1, " %c %*d %*d %*d %*d %*d %*u %*u %*u %*u %*u %*u %*u %*d %*d %*d %*d"
             " %*d %*d %llu", &state, &start) != 2)
    return 0;
  if (state == 'Z' || state == 'X') return 0; /* dead, not yet reaped */
  return seconds(CLOCK_BOOTTIME) - (double)start / (double)sysconf(_SC_CLK_TCK) + START_SLACK_S >=
         seconds(CLOCK_REALTIME) -
             ((double)st->st_mtim.tv_sec + (double)st->st_mtim.tv_nsec / 1e9);
}

/* 1 alive, 0 not; `serving` asks more of a holder: that its pid is the one its file names.
 * A starting firmware takes the lock, clears the READY a killed predecessor left, and only
 * then writes its pid (dpm.image.ExclusiveLock): READY read after a "serving" is its own
 * (host_api.liveness.firmware_serving). */
static int firmware_holds(const char *path, int serving) {
  char device[64];
  struct stat st;
  long holder = 0;
  int alive = 0, fd, held;
  if (stat(path, &st) != 0) return 0;
  snprintf(device, sizeof device, "%02x:%02x:%lu", major(st.st_dev), minor(st.st_dev),
           (unsigned long)st.st_ino);
  held = lock_table_holds(device, &holder);
  if (held == 0) return recorded_pid_wrote(path, &st);
  if (held > 0) return !serving || holder == 0 || holder == recorded_pid(path);
  fd = open(path, O_RDONLY | O_CLOEXEC);
  if (fd < 0) return 0;
  if (flock(fd, LOCK_SH | LOCK_NB) != 0) alive = errno == EWOULDBLOCK;
  close(fd);
  return alive;
}

static int firmware_alive(const char *path) { return firmware_holds(path, 0); }

/* A wait's time-out code, or DRV_DEV_NOT_READY when the firmware died meanwhile. */
static short timed_out(const cifemu_board *b, short code) {
  return firmware_alive(b->firmware_lock) ? code : DRV_DEV_NOT_READY;
}

static void lock_path(char *out, size_t size, unsigned short number, const char *what) {
  snprintf(out, size, "%s/board%u.%s.lock", directory, (unsigned)number, what);
}

static void board_close(cifemu_board *b) {
  cifemu_bell_close(&b->bell);
  cifemu_chanlock_close(&b->put_lock);
  cifemu_chanlock_close(&b->get_lock);
  cifemu_chanlock_close(&b->io_lock);
  cifemu_txn_close(&b->txn);
  munmap(b->mm, DPM_SIZE);
  free(b);
}

/* The driver's checks: DPM access (test pattern), READY, the DPM size. */
static short check_card(unsigned char *mm) {
  static const unsigned char pattern[3] = {0x55, 0xAA, 0x00};
  unsigned char identifier[3], readback[3];
  memcpy(identifier, mm + OFS_DEV_IDENTIFIER, 3);
  if (memcmp(identifier, "CIF", 3) != 0) return DRV_DEV_DPM_ACCESS_ERROR;
  memcpy(mm + OFS_DEV_IDENTIFIER, pattern, 3);
  memcpy(readback, mm + OFS_DEV_IDENTIFIER, 3);
  memcpy(mm + OFS_DEV_IDENTIFIER, identifier, 3);
  if (memcmp(readback, pattern, 3) != 0) return DRV_DEV_DPM_ACCESS_ERROR;
  if (!(__atomic_load_n(mm + OFS_HOST_FLAGS, __ATOMIC_ACQUIRE) & FL_READY)) {
    unsigned char error = mm[OFS_RCS_ERROR];
    return (short)(error > 0 && error < 250 ? DRV_RCS_ERROR_OFFSET + error : DRV_DEV_NOT_READY);
  }
  if ((unsigned)mm[OFS_DPM_SIZE] * 1024u != DPM_SIZE) return DRV_DEV_DPMSIZE_MISMATCH;
  return DRV_NO_ERROR;
}

/* ---- driver and board ----------------------------------------------------- */


/* What one lock of a board does with its file: open it, or reopen it in a forked child. */
typedef int (*chanlock_fn)(cifemu_chanlock *lock, const char *path);
typedef int (*txn_fn)(cifemu_txn *txn, const char *path);

/* Every lock of board b, in turn, until one fails: 0, else -1. */
static int each_lock(cifemu_board *b, chanlock_fn channel, txn_fn transaction) {
  char path[PATH_MAX + 32];
  /* put and get: thread locks only, inside the transaction lock (chanlock.h) */
  if (channel(&b->put_lock, NULL) != 0 || channel(&b->get_lock, NULL) != 0) return -1;
  lock_path(path, sizeof path, b->number, "io");
  if (channel(&b->io_lock, path) != 0) return -1;
  lock_path(path, sizeof path, b->number, "transaction");
  return transaction(&b->txn, path);
}

/* [ours] A child forked after DevInitBoard gets lock files, locks and a doorbell of its
   own: the descriptors it inherited share their flocks (and rings) with the parent, so
   both would be inside a channel at once and read each other's answers. The parent's
   threads do not exist in the child: the mutexes one of them held are made anew. A board
   whose lock files cannot be opened again is closed in the child (-32 there). */
static void child_after_fork(void) {
  char path[PATH_MAX + 16];
  int n;
  pthread_mutex_init(&driver_lock, NULL);
  pthread_mutex_init(&table_lock, NULL);
  /* the calls inside a closed board were the parent's threads': it goes now */
  while (closing_boards != NULL) {
    cifemu_board *b = closing_boards;
    closing_boards = b->next_closing;
    board_close(b);
  }
  for (n = 0; n < MAX_DEV_BOARDS; n++) {
    cifemu_board *b = boards[n];
    if (b == NULL) continue;
    b->users = 0;
    if (each_lock(b, cifemu_chanlock_reopen, cifemu_txn_reopen) != 0) {
      boards[n] = NULL;
      board_close(b);
      continue;
    }
    cifemu_bell_close(&b->bell);
    image_path(path, sizeof path, b->number);
    if (cifemu_bell_open(&b->bell, path) == 0)
      cifemu_bell_ring(&b->bell); /* introduces the child to the device */
  }
}

static pthread_once_t fork_handler_once = PTHREAD_ONCE_INIT;
static void register_fork_handler(void) { pthread_atfork(NULL, NULL, child_after_fork); }

CIF_API short DevOpenDriver(void) {
  const char *env = getenv("CIF_DPM_DIR");
  const char *path = env != NULL ? env : DEFAULT_DPM_DIR;
  struct stat st;
  short rc = DRV_NO_ERROR;
  pthread_once(&fork_handler_once, register_fork_handler);
  pthread_mutex_lock(&driver_lock);
  if (strlen(path) >= sizeof directory - 16 || stat(path, &st) != 0 || !S_ISDIR(st.st_mode)) {
    rc = DRV_USR_OPEN_ERROR;
  } else if (open_count > 0 && strcmp(directory, path) != 0) {
    rc = DRV_USR_OPEN_ERROR; /* one process, one image directory */
  } else {
    if (open_count == 0) {
      strcpy(directory, path);
      hDevDrv = open(path, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    }
    open_count++;
  }
  pthread_mutex_unlock(&driver_lock);
  return rc;
}

CIF_API short DevCloseDriver(void) {
  short rc = DRV_NO_ERROR;
  int n;
  pthread_mutex_lock(&driver_lock);
  if (open_count == 0) {
    rc = DRV_USR_NOT_INITIALIZED;
  } else if (--open_count == 0) {
    for (n = 0; n < MAX_DEV_BOARDS; n++) {
      cifemu_counters *c = &counters[n];
      board_remove((unsigned short)n);
      /* a call still inside a closed board may count: atomically, as it does */
      __atomic_store_n(&c->open, 0u, __ATOMIC_RELAXED);
      __atomic_store_n(&c->close, 0u, __ATOMIC_RELAXED);
      __atomic_store_n(&c->read, 0u, __ATOMIC_RELAXED);
      __atomic_store_n(&c->write, 0u, __ATOMIC_RELAXED);
      __atomic_store_n(&c->irq, 0u, __ATOMIC_RELAXED);
      __atomic_store_n(&c->io, 0u, __ATOMIC_RELAXED);
      __atomic_store_n(&c->last_function, 0, __ATOMIC_RELAXED);
    }
    if (hDevDrv >= 0) close(hDevDrv);
    hDevDrv = -1;
  }
  pthread_mutex_unlock(&driver_lock);
  return rc;
}

/* BOARD_INFO; the caller holds driver_lock. */
static short board_info(BOARD_INFO *pvData) {
  char path[PATH_MAX + 16];
  unsigned short n, detected = 0;
  if (open_count == 0) return DRV_USR_NOT_INITIALIZED;
  if (pvData == NULL) return DRV_USR_BUF_PTR_NULL;
  memset(pvData, 0, sizeof *pvData);
  memcpy(pvData->abDriverVersion, DRIVER_VERSION, sizeof DRIVER_VERSION - 1);
  for (n = 0; n < MAX_DEV_BOARDS; n++) {
    int available;
    image_path(path, sizeof path, n);
    available = access(path, F_OK) == 0;
    detected = (unsigned short)(detected + available);
    pvData->tBoard[n].usBoard = n;
    pvData->tBoard[n].usAvailable = (unsigned short)available;
  }
  pvData->usBoards_detected = detected;
  return DRV_NO_ERROR;
}

CIF_API short DevGetBoardInfo(BOARD_INFO *pvData) {
  short rc;
  pthread_mutex_lock(&driver_lock);
  rc = board_info(pvData);
  pthread_mutex_unlock(&driver_lock);
  return rc;
}

static void fill_driver_info(cifemu_board *b, DRIVERINFO *info);

/* [ours] BOARD_INFO's entries, and for each initialised board its DRIVERINFO and the
   card's information areas; boards this process has not initialised stay zero. */
CIF_API short DevGetBoardInfoEx(void *pvData) {
  BOARD_INFOEX *ex = (BOARD_INFOEX *)pvData;
  BOARD_INFO info;
  short rc;
  int n;
  pthread_mutex_lock(&driver_lock);
  rc = pvData == NULL && open_count > 0 ? DRV_USR_BUF_PTR_NULL : board_info(&info);
  if (rc == DRV_NO_ERROR) {
    memset(ex, 0, sizeof *ex);
    memcpy(ex->abDriverVersion, info.abDriverVersion, sizeof ex->abDriverVersion);
    for (n = 0; n < MAX_DEV_BOARDS; n++) {
      cifemu_board *b = boards[n];
      ex->tBoard[n].usBoard = info.tBoard[n].usBoard;
      ex->tBoard[n].usAvailable = info.tBoard[n].usAvailable;
      if (b == NULL) continue;
      fill_driver_info(b, &ex->tBoard[n].tDriverInfo);
      memcpy(&ex->tBoard[n].tFirmware, b->mm + OFS_FIRMWARE_INFO, sizeof(FIRMWAREINFO));
      memcpy(&ex->tBoard[n].tDeviceInfo, b->mm + OFS_DEV_INFO, sizeof(DEVINFO));
      memcpy(&ex->tBoard[n].tRcsInfo, b->mm + OFS_RCS_INFO, sizeof(RCSINFO));
      memcpy(&ex->tBoard[n].tVersion, b->mm + OFS_VERSION_INFO, sizeof(VERSIONINFO));
    }
  }
  pthread_mutex_unlock(&driver_lock);
  return rc;
}

/* [ours] Linux only: polling (0) or interrupt (1). The emulated card always has its
   doorbell with polling beside it, so both modes are accepted and usIrq reads 0. */
CIF_API short DevSetOpMode(unsigned short usBoard, unsigned short usMode, unsigned short *usIrq) {
  short rc;
  cifemu_board *b = cifemu_board_enter(usBoard, &rc);
  if (b == NULL) return rc;
  cifemu_board_leave(b);
  if (usMode != POLLING_MODE && usMode != INTERRUPT_MODE) return DRV_USR_MODE_INVALID;
  if (usIrq != NULL) *usIrq = 0;
  return DRV_NO_ERROR;
}

CIF_API short DevInitBoard(unsigned short usDevNumber) {
  char path[PATH_MAX + 16], firmware_lock[PATH_MAX + 32];
  unsigned char *mm;
  cifemu_board *b;
  struct stat st;
  short rc;
  int fd, serving;
  if (usDevNumber >= MAX_DEV_BOARDS) return DRV_USR_DEV_NUMBER_INVALID;
  pthread_mutex_lock(&driver_lock);
  if (open_count == 0) {
    rc = DRV_USR_NOT_INITIALIZED;
    goto out;
  }
  rc = DRV_NO_ERROR;
  if (boards[usDevNumber] != NULL) goto out;
  image_path(path, sizeof path, usDevNumber);
  if (access(path, F_OK) != 0) {
    rc = DRV_USR_DEV_NUMBER_INVALID;
    goto out;
  }
  fd = open(path, O_RDWR | O_CLOEXEC);
  if (fd < 0 || fstat(fd, &st) != 0 || st.st_size < DPM_SIZE) {
    if (fd >= 0) close(fd);
    rc = DRV_DEV_DPM_ACCESS_ERROR;
    goto out;
  }
  mm = (unsigned char *)mmap(NULL, DPM_SIZE, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  close(fd);
  if (mm == MAP_FAILED) {
    rc = DRV_DEV_DPM_ACCESS_ERROR;
    goto out;
  }
  /* [ours] READY left behind by a killed firmware: who serves is asked first, READY after */
  lock_path(firmware_lock, sizeof firmware_lock, usDevNumber, "firmware");
  serving = firmware_holds(firmware_lock, 1);
  rc = check_card(mm);
  if (rc == DRV_NO_ERROR && !serving) rc = DRV_DEV_NOT_READY;
  if (rc != DRV_NO_ERROR) {
    munmap(mm, DPM_SIZE);
    goto out;
  }
  b = (cifemu_board *)calloc(1, sizeof *b);
  if (b != NULL) { /* nothing open yet: closing it must not close descriptor 0 */
    b->bell.fd = b->put_lock.fd = b->get_lock.fd = b->io_lock.fd = -1;
    b->txn.lock.fd = -1;
    b->number = usDevNumber;
    memcpy(b->firmware_lock, firmware_lock, sizeof firmware_lock);
  }
  if (b == NULL || cifemu_bell_open(&b->bell, path) != 0 ||
      each_lock(b, cifemu_chanlock_open, cifemu_txn_open) != 0) {
    /* [ours] no socket or lock file for this host: the board cannot be shared safely */
    if (b != NULL) {
      b->mm = mm;
      board_close(b);
    } else {
      munmap(mm, DPM_SIZE);
    }
    rc = DRV_USR_INIT_DRV_ERROR;
    goto out;
  }
  b->mm = mm;
  b->counters = &counters[usDevNumber];
  count(&b->counters->open);
  __atomic_store_n(&b->counters->last_function, FKT_OPEN, __ATOMIC_RELAXED);
  cifemu_bell_ring(&b->bell); /* introduces this host to the device */
  pthread_mutex_lock(&table_lock);
  boards[usDevNumber] = b;
  pthread_mutex_unlock(&table_lock);
out:
  pthread_mutex_unlock(&driver_lock);
  return rc;
}

/* Returns at once: the calls inside the board end as they would have (their message or
   their time-out), calls after it get -32, the last one out unmaps the board. */
CIF_API short DevExitBoard(unsigned short usDevNumber) {
  short rc;
  if (usDevNumber >= MAX_DEV_BOARDS) return DRV_USR_DEV_NUMBER_INVALID;
  pthread_mutex_lock(&driver_lock);
  rc = boards[usDevNumber] != NULL ? DRV_NO_ERROR : DRV_USR_NOT_INITIALIZED;
  if (rc == DRV_NO_ERROR) {
    count(&counters[usDevNumber].close);
    __atomic_store_n(&counters[usDevNumber].last_function, FKT_CLOSE, __ATOMIC_RELAXED);
    rc = board_remove(usDevNumber);
  }
  pthread_mutex_unlock(&driver_lock);
  return rc;
}

/* ---- mailboxes ------------------------------------------------------------ */

static short put_message(cifemu_board *b, MSG_STRUC *ptMessage, unsigned long ulTimeout) {
  short rc;
  long long deadline = cifemu_now_ns();
  if (ptMessage == NULL) return DRV_USR_MSG_BUF_NULL_PTR;
  if (!cifemu_txn_enter(&b->txn, ulTimeout)) return DRV_CMD_ACTIVE;
  if (!cifemu_chanlock_acquire(&b->put_lock, remaining_ms(deadline, ulTimeout))) {
    cifemu_txn_leave(&b->txn);
    return DRV_CMD_ACTIVE;
  }
  if (!wait_for_ringing(b, cond_free, CH_DEV_MBX, remaining_ms(deadline, ulTimeout), 1)) {
    rc = ulTimeout == 0 ? DRV_DEV_MAILBOX_FULL : timed_out(b, DRV_DEV_PUT_TIMEOUT);
  } else {
    /* the message is ln + 8 bytes; the caller's buffer may be no longer than that */
    memcpy(b->mm + OFS_DEV_MBX, ptMessage, 8u + ptMessage->ln);
    /* recorded before the card can see it: a host killed now leaves it in the ledger */
    cifemu_txn_sent(&b->txn, (const unsigned char *)ptMessage);
    change_dev_flags(b, 0, 0, FL_DEVCOM, 1);
    count(&b->counters->write);
    __atomic_store_n(&b->counters->last_function, FKT_WRITE, __ATOMIC_RELAXED);
    rc = DRV_NO_ERROR;
  }
  cifemu_chanlock_release(&b->put_lock);
  cifemu_txn_leave(&b->txn);
  return rc;
}

CIF_API short DevPutMessage(unsigned short usDevNumber, MSG_STRUC *ptMessage,
                            unsigned long ulTimeout) {
  short rc;
  cifemu_board *b = cifemu_ready_board(usDevNumber, &rc);
  if (b == NULL) return rc;
  rc = put_message(b, ptMessage, ulTimeout);
  cifemu_board_leave(b);
  return rc;
}

/* [ours] Answers to another host's requests (it died, or gave the board up after a get
   timed out) are read and discarded (with the handshake) within the caller's time-out,
   never returned. */
static short get_message(cifemu_board *b, unsigned short usSize, MSG_STRUC *ptMessage,
                         unsigned long ulTimeout) {
  short rc;
  long long deadline = cifemu_now_ns();
  if (ptMessage == NULL) return DRV_USR_MSG_BUF_NULL_PTR;
  /* a host expecting nothing still waits for other hosts' transactions to finish */
  if (!cifemu_txn_enter(&b->txn, ulTimeout)) return DRV_CMD_ACTIVE;
  if (!cifemu_chanlock_acquire(&b->get_lock, remaining_ms(deadline, ulTimeout))) {
    cifemu_txn_leave(&b->txn);
    return DRV_CMD_ACTIVE;
  }
  for (;;) {
    unsigned char header[8];
    unsigned length;
    int stale;
    if (!wait_for(b, cond_pending, CH_HOST_MBX, remaining_ms(deadline, ulTimeout))) {
      rc = ulTimeout == 0 ? DRV_DEV_GET_NO_MESSAGE : timed_out(b, DRV_DEV_GET_TIMEOUT);
      /* [ours] answers that did not come in time no longer keep the board from other
         hosts: this host reads them if it holds the board when they come, another host
         that took it meanwhile discards them */
      if (ulTimeout != 0) cifemu_txn_give_up(&b->txn);
      break;
    }
    memcpy(header, b->mm + OFS_PC_MBX, sizeof header);
    length = 8u + header[2];
    stale = cifemu_txn_is_stale(&b->txn, header);
    if (!stale && length > usSize) {
      rc = DRV_USR_MSG_BUF_TOO_SHORT; /* the message stays in the mailbox */
      break;
    }
    if (!stale) memcpy(ptMessage, b->mm + OFS_PC_MBX, length);
    /* The device polls anyway; a ring only speeds up answers it has queued. */
    change_dev_flags(b, 0, 0, FL_HOSTACK,
                     stale || __atomic_load_n(&b->bell.device_wants_ack, __ATOMIC_RELAXED));
    /* after the handshake: a host killed in between leaves a discarded answer's request
       in the ledger, never an answer nobody discards */
    cifemu_txn_answered(&b->txn, header);
    if (stale) continue;
    count(&b->counters->read);
    __atomic_store_n(&b->counters->last_function, FKT_READ, __ATOMIC_RELAXED);
    rc = DRV_NO_ERROR;
    break;
  }
  cifemu_chanlock_release(&b->get_lock);
  cifemu_txn_leave(&b->txn);
  return rc;
}

CIF_API short DevGetMessage(unsigned short usDevNumber, unsigned short usSize,
                            MSG_STRUC *ptMessage, unsigned long ulTimeout) {
  short rc;
  cifemu_board *b;
  if (usSize == 0 || usSize > MSG_BUFFER_SIZE) return DRV_USR_SIZE_INVALID;
  b = cifemu_ready_board(usDevNumber, &rc);
  if (b == NULL) return rc;
  rc = get_message(b, usSize, ptMessage, ulTimeout);
  cifemu_board_leave(b);
  return rc;
}

CIF_API short DevGetMBXState(unsigned short usDevNumber, unsigned short *pusDevMBXState,
                             unsigned short *pusHostMBXState) {
  short rc;
  unsigned char host, dev;
  cifemu_board *b = cifemu_ready_board(usDevNumber, &rc);
  if (b == NULL) return rc;
  host = host_flags(b);
  dev = dev_flags(b);
  cifemu_board_leave(b);
  if (pusDevMBXState == NULL || pusHostMBXState == NULL) return DRV_USR_BUF_PTR_NULL;
  *pusDevMBXState = (host ^ dev) & CH_DEV_MBX ? DEVICE_MBX_FULL : DEVICE_MBX_EMPTY;
  *pusHostMBXState = (host ^ dev) & CH_HOST_MBX ? HOST_MBX_FULL : HOST_MBX_EMPTY;
  return DRV_NO_ERROR;
}

/* [ours] a copy of both mailboxes as they are, without any handshake: usHostSize bytes
   of the host mailbox (PcMbx) and usDevSize bytes of the device mailbox (DevMbx),
   each 1..288 (0 -> -42, larger -> -43). */
CIF_API short DevGetMBXData(unsigned short usDevNumber, unsigned short usHostSize,
                            void *pvHostData, unsigned short usDevSize, void *pvDevData) {
  short rc;
  cifemu_board *b = cifemu_ready_board(usDevNumber, &rc);
  if (b == NULL) return rc;
  if (usHostSize == 0 || usDevSize == 0) rc = DRV_USR_SIZE_ZERO;
  else if (usHostSize > MSG_BUFFER_SIZE || usDevSize > MSG_BUFFER_SIZE) rc = DRV_USR_SIZE_TOO_LONG;
  else if (pvHostData == NULL || pvDevData == NULL) rc = DRV_USR_BUF_PTR_NULL;
  else {
    memcpy(pvHostData, b->mm + OFS_PC_MBX, usHostSize);
    memcpy(pvDevData, b->mm + OFS_DEV_MBX, usDevSize);
    rc = DRV_NO_ERROR;
  }
  cifemu_board_leave(b);
  return rc;
}

/* ---- process data --------------------------------------------------------- */

/* [ours] A host that spins on the uncontrolled exchange lets the card run, as the Python
   driver's MappedBoard.poll_inputs (docs/dpm.md section 2): every POLLS_BEFORE_YIELD-th
   read-only call in a row that reads the same inputs, within POLL_WINDOW_NS of the first,
   gives up the CPU. The emulated card's threads run on the host's CPUs; a wake-up of theirs
   queued behind a spinning host waited for the end of its time slice. Per thread: a
   thread polls, and it needs no lock. */
static __thread struct {
  const cifemu_board *board;
  unsigned short offset, size;
  unsigned polls;
  long long since;
  unsigned char inputs[IO_AREA_SIZE];
} polled;

static void poll_inputs(const cifemu_board *b, unsigned short offset, unsigned short size,
                        const void *inputs) {
  if (polled.board != b || polled.offset != offset || polled.size != size ||
      memcmp(polled.inputs, inputs, size) != 0) {
    polled.board = b;
    polled.offset = offset;
    polled.size = size;
    polled.polls = 0;
    memcpy(polled.inputs, inputs, size);
    return;
  }
  if (++polled.polls == 1) {
    polled.since = cifemu_now_ns();
  } else if (polled.polls >= POLLS_BEFORE_YIELD) {
    polled.polls = 0;
    if (cifemu_now_ns() - polled.since < POLL_WINDOW_NS) sched_yield();
  }
}

static short exchange(cifemu_board *b, unsigned mode, unsigned short usSendOffset,
                      unsigned short usSendSize, const void *pvSendData,
                      unsigned short usReceiveOffset, unsigned short usReceiveSize,
                      void *pvReceiveData, unsigned long ulTimeout) {
  short rc;
  if (usSendSize && (unsigned)usSendOffset + usSendSize > IO_AREA_SIZE)
    return DRV_USR_SENDSIZE_TOO_LONG;
  if (usReceiveSize && (unsigned)usReceiveOffset + usReceiveSize > IO_AREA_SIZE)
    return DRV_USR_RECVSIZE_TOO_LONG;
  if (usSendSize && pvSendData == NULL) return DRV_USR_SENDBUF_PTR_NULL;
  if (usReceiveSize && pvReceiveData == NULL) return DRV_USR_RECVBUF_PTR_NULL;
  if (!ready(b)) return DRV_DEV_NOT_READY;
  if (mode < 1 || mode > 5) return DRV_DEV_COM_MODE_UNKNOWN;
  if (mode == 3) { /* uncontrolled: no handshake, just the copy */
    /* [ours] the card sends changed outputs when rung (docs/dpm.md 2) */
    if (usSendSize && memcmp(b->mm + OFS_SND_PD + usSendOffset, pvSendData, usSendSize)) {
      memcpy(b->mm + OFS_SND_PD + usSendOffset, pvSendData, usSendSize);
      cifemu_bell_ring(&b->bell);
    }
    if (usReceiveSize) {
      memcpy(pvReceiveData, b->mm + OFS_RCV_PD + usReceiveOffset, usReceiveSize);
      if (!usSendSize) poll_inputs(b, usReceiveOffset, usReceiveSize, pvReceiveData);
    }
    rc = DRV_NO_ERROR;
  } else {
    int device_controlled = mode == 1 || mode == 2;
    if (!cifemu_chanlock_acquire(&b->io_lock, ulTimeout)) return DRV_CMD_ACTIVE;
    /* Device-controlled: the host's turn is while the bits differ; host-controlled:
       while they are equal (the device answered). */
    if (wait_for(b, cond_pd_turn, device_controlled, ulTimeout)) {
      __atomic_thread_fence(__ATOMIC_ACQUIRE);
      if (usSendSize) memcpy(b->mm + OFS_SND_PD + usSendOffset, pvSendData, usSendSize);
      if (usReceiveSize)
        memcpy(pvReceiveData, b->mm + OFS_RCV_PD + usReceiveOffset, usReceiveSize);
      __atomic_thread_fence(__ATOMIC_RELEASE);
      change_dev_flags(b, 0, 0, FL_PDCOM, 1);
      rc = DRV_NO_ERROR;
    } else {
      rc = ulTimeout == 0 ? DRV_DEV_EXCHANGE_FAILED : timed_out(b, DRV_DEV_EXCHANGE_TIMEOUT);
    }
    cifemu_chanlock_release(&b->io_lock);
  }
  count(&b->counters->io);
  __atomic_store_n(&b->counters->last_function, FKT_IO, __ATOMIC_RELAXED);
  if (!(host_flags(b) & FL_COM)) rc = DRV_DEV_NO_COM_FLAG;
  return rc;
}

static unsigned driver_mode(const cifemu_board *b) { return b->mm[OFS_DRIVER_TYPE] >> 4; }

CIF_API short DevExchangeIO(unsigned short usDevNumber, unsigned short usSendOffset,
                            unsigned short usSendSize, void *pvSendData,
                            unsigned short usReceiveOffset, unsigned short usReceiveSize,
                            void *pvReceiveData, unsigned long ulTimeout) {
  short rc;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  if (b == NULL) return rc;
  rc = exchange(b, driver_mode(b), usSendOffset, usSendSize, pvSendData, usReceiveOffset,
                usReceiveSize, pvReceiveData, ulTimeout);
  cifemu_board_leave(b);
  return rc;
}

CIF_API short DevExchangeIOEx(unsigned short usDevNumber, unsigned short usMode,
                              unsigned short usSendOffset, unsigned short usSendSize,
                              void *pvSendData, unsigned short usReceiveOffset,
                              unsigned short usReceiveSize, void *pvReceiveData,
                              unsigned long ulTimeout) {
  short rc;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  if (b == NULL) return rc;
  rc = usMode > 4 ? DRV_USR_MODE_INVALID
                  : exchange(b, usMode + 1u, usSendOffset, usSendSize, pvSendData,
                             usReceiveOffset, usReceiveSize, pvReceiveData, ulTimeout);
  cifemu_board_leave(b);
  return rc;
}

CIF_API short DevExchangeIOErr(unsigned short usDevNumber, unsigned short usSendOffset,
                               unsigned short usSendSize, void *pvSendData,
                               unsigned short usReceiveOffset, unsigned short usReceiveSize,
                               void *pvReceiveData, COMSTATE *ptState,
                               unsigned long ulTimeout) {
  short rc;
  unsigned state_mode;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  if (b == NULL) {
    if (ptState != NULL) memset(ptState, 0, sizeof *ptState);
    return rc;
  }
  if (ptState == NULL) {
    cifemu_board_leave(b);
    return DRV_USR_BUF_PTR_NULL;
  }
  rc = DevExchangeIO(usDevNumber, usSendOffset, usSendSize, pvSendData, usReceiveOffset,
                     usReceiveSize, pvReceiveData, ulTimeout);
  memset(ptState, 0, sizeof *ptState);
  state_mode = b->mm[OFS_DRIVER_TYPE] & 0x0F;
  ptState->usMode = (unsigned short)state_mode;
  if (state_mode == STATE_MODE_4) {
    if (pending(b, CH_STATE)) {
      memcpy(ptState->abState, b->mm + OFS_TASK2_STATE, TASK_AREA_SIZE);
      ptState->usStateFlag = 1;
      change_dev_flags(b, 0, 0, FL_STATEACK, 1);
    }
  } else if (state_mode == STATE_MODE_3) {
    ptState->usStateFlag = (host_flags(b) & FL_STATECOM) ? 1 : 0;
    memcpy(ptState->abState, b->mm + OFS_TASK2_STATE, TASK_AREA_SIZE);
  } else {
    ptState->usStateFlag = STATE_FLAG_UNKNOWN;
  }
  cifemu_board_leave(b);
  return rc;
}

CIF_API short DevReadSendData(unsigned short usDevNumber, unsigned short usOffset,
                              unsigned short usSize, void *pvData) {
  short rc;
  cifemu_board *b = cifemu_ready_board(usDevNumber, &rc);
  if (b == NULL) return rc;
  if ((unsigned)usOffset + usSize > IO_AREA_SIZE) rc = DRV_USR_SIZE_TOO_LONG;
  else if (!(host_flags(b) & FL_COM)) rc = DRV_DEV_NO_COM_FLAG;
  else if (usSize && pvData == NULL) rc = DRV_USR_BUF_PTR_NULL;
  else {
    if (usSize) memcpy(pvData, b->mm + OFS_SND_PD + usOffset, usSize);
    rc = DRV_NO_ERROR;
  }
  cifemu_board_leave(b);
  return rc;
}

/* ---- control -------------------------------------------------------------- */

static short reset(cifemu_board *b, unsigned short usMode, unsigned long ulTimeout) {
  unsigned char request;
  long long deadline;
  long long remaining;
  switch (usMode) {
    case COLDSTART: request = FL_RESET; break;
    case WARMSTART: request = FL_INIT; break;
    case BOOTSTART: request = FL_RESET | FL_INIT; break;
    default: return DRV_USR_MODE_INVALID;
  }
  if (ulTimeout > 2000000000UL) ulTimeout = 2000000000UL;
  change_dev_flags(b, request, 0, 0, 1);
  deadline = cifemu_now_ns() + (long long)ulTimeout * 1000000LL;
  if (!wait_for(b, cond_reset_done, 0, ulTimeout)) return timed_out(b, DRV_DEV_RESET_TIMEOUT);
  remaining = (deadline - cifemu_now_ns()) / 1000000LL;
  if (!wait_for(b, cond_ready, 0, remaining > 0 ? (unsigned long)remaining : 0UL))
    return timed_out(b, DRV_DEV_RESET_TIMEOUT);
  return DRV_NO_ERROR;
}

CIF_API short DevReset(unsigned short usDevNumber, unsigned short usMode, unsigned long ulTimeout) {
  short rc;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  if (b == NULL) return rc;
  rc = reset(b, usMode, ulTimeout);
  cifemu_board_leave(b);
  return rc;
}

static short set_host_state(cifemu_board *b, unsigned short usMode, unsigned long ulTimeout) {
  if (usMode == HOST_READY) change_dev_flags(b, 0, FL_NOTREADY, 0, 1);
  else if (usMode == HOST_NOT_READY) change_dev_flags(b, FL_NOTREADY, 0, 0, 1);
  else return DRV_USR_MODE_INVALID;
  if (ulTimeout > 0 &&
      !wait_for(b, cond_host_bit, FL_COM | (usMode == HOST_READY) << 8, ulTimeout))
    return DRV_DEV_NO_COM_FLAG;
  return DRV_NO_ERROR;
}

CIF_API short DevSetHostState(unsigned short usDevNumber, unsigned short usMode,
                              unsigned long ulTimeout) {
  short rc;
  cifemu_board *b = cifemu_ready_board(usDevNumber, &rc);
  if (b == NULL) return rc;
  rc = set_host_state(b, usMode, ulTimeout);
  cifemu_board_leave(b);
  return rc;
}

CIF_API short DevTriggerWatchDog(unsigned short usDevNumber, unsigned short usFunction,
                                 unsigned short *usDevWatchDog) {
  short rc;
  unsigned char value;
  cifemu_board *b = cifemu_ready_board(usDevNumber, &rc);
  if (b == NULL) return rc;
  if (usFunction != WATCHDOG_START && usFunction != WATCHDOG_STOP) {
    rc = DRV_USR_MODE_INVALID;
  } else if (usDevWatchDog == NULL) {
    rc = DRV_USR_BUF_PTR_NULL;
  } else {
    value = usFunction == WATCHDOG_START ? flag_get(b, OFS_HOST_WATCHDOG) : 0;
    __atomic_store_n(b->mm + OFS_DEV_WATCHDOG, value, __ATOMIC_RELEASE);
    cifemu_bell_ring(&b->bell);
    *usDevWatchDog = value;
  }
  cifemu_board_leave(b);
  return rc;
}

/* Set (1) or clear (0) SPCCOM; returns the SPCACK level once the card mirrored it.
   [ours] the call waits up to 100 ms for the mirror, then reports the level as it is. */
CIF_API short DevSpecialControl(unsigned short usDevNumber, unsigned short usMode,
                                unsigned short *pusCtrlAck) {
  short rc;
  cifemu_board *b = cifemu_ready_board(usDevNumber, &rc);
  if (b == NULL) return rc;
  if (usMode != SPECIAL_CONTROL_SET && usMode != SPECIAL_CONTROL_CLEAR) {
    rc = DRV_USR_MODE_INVALID;
  } else if (pusCtrlAck == NULL) {
    rc = DRV_USR_BUF_PTR_NULL;
  } else {
    if (usMode == SPECIAL_CONTROL_SET) change_dev_flags(b, FL_SPCCOM, 0, 0, 1);
    else change_dev_flags(b, 0, FL_SPCCOM, 0, 1);
    wait_for(b, cond_host_bit, FL_SPCACK | (usMode == SPECIAL_CONTROL_SET) << 8,
             SPECIAL_CONTROL_WAIT_MS);
    *pusCtrlAck = (host_flags(b) & FL_SPCACK) ? 1 : 0;
  }
  cifemu_board_leave(b);
  return rc;
}

/* ---- information and parameters ------------------------------------------- */

static void fill_driver_info(cifemu_board *b, DRIVERINFO *info) {
  const cifemu_counters *c = b->counters;
  unsigned char host = host_flags(b), dev = dev_flags(b);
  memset(info, 0, sizeof *info);
  info->ulOpenCnt = __atomic_load_n(&c->open, __ATOMIC_RELAXED);
  info->CloseCnt = __atomic_load_n(&c->close, __ATOMIC_RELAXED);
  info->ulReadCnt = __atomic_load_n(&c->read, __ATOMIC_RELAXED);
  info->ulWriteCnt = __atomic_load_n(&c->write, __ATOMIC_RELAXED);
  info->ulIRQCnt = __atomic_load_n(&c->irq, __ATOMIC_RELAXED);
  info->bInitMsgFlag = (host & FL_READY) ? 1 : 0;
  info->bReadMsgFlag = ((host ^ dev) & CH_HOST_MBX) ? 1 : 0;
  info->bWriteMsgFlag = ((host ^ dev) & CH_DEV_MBX) ? 1 : 0;
  info->bLastFunction = __atomic_load_n(&c->last_function, __ATOMIC_RELAXED);
  info->bHostFlags = host;
  info->bMyDevFlags = dev;
  info->bExIOFlag = (host & FL_COM) ? 1 : 0;
  info->ulExIOCnt = __atomic_load_n(&c->io, __ATOMIC_RELAXED);
}

CIF_API short DevGetInfo(unsigned short usDevNumber, unsigned short usFunction,
                         unsigned short usSize, void *pvData) {
  static const unsigned short sizes[9] = {0, 33, 32, 32, 112, 8, 6, 6, IO_AREA_SIZE};
  static const unsigned short offsets[9] = {0, 0, OFS_VERSION_INFO, OFS_FIRMWARE_INFO,
                                            OFS_TASK_INFO, OFS_RCS_INFO, OFS_DEV_INFO, 0,
                                            OFS_SND_PD};
  short rc;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  if (b == NULL) return rc;
  if (usSize == 0) rc = DRV_USR_SIZE_ZERO;
  else if (usFunction < GET_DRIVER_INFO || usFunction > GET_IO_SEND_DATA)
    rc = DRV_USR_INFO_AREA_INVALID;
  else if (usSize > sizes[usFunction]) rc = DRV_USR_SIZE_TOO_LONG;
  else if (pvData == NULL) rc = DRV_USR_BUF_PTR_NULL;
  else if (usFunction == GET_DRIVER_INFO) {
    DRIVERINFO info;
    fill_driver_info(b, &info);
    memcpy(pvData, &info, usSize);
  } else if (usFunction == GET_IO_INFO) {
    IOINFO info;
    info.bComBit = (host_flags(b) & FL_COM) ? 1 : 0;
    info.bIOExchangeMode = (unsigned char)driver_mode(b);
    info.ulIOExchangeCnt = __atomic_load_n(&b->counters->io, __ATOMIC_RELAXED);
    memcpy(pvData, &info, usSize);
  } else {
    memcpy(pvData, b->mm + offsets[usFunction], usSize);
  }
  cifemu_board_leave(b);
  return rc;
}

enum task_copy { READ_STATE, READ_PARAMETER, WRITE_PARAMETER };

/* Task 1's or task 2's state or parameter area, copied out of or into the image. */
static short task_area(unsigned short usDevNumber, unsigned short usNumber,
                       unsigned short usSize, void *pvData, enum task_copy copy) {
  unsigned offset;
  short rc;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  if (b == NULL) return rc;
  if (usNumber != 1 && usNumber != 2) rc = DRV_USR_NUMBER_INVALID;
  else if (usSize == 0) rc = DRV_USR_SIZE_ZERO;
  else if (usSize > TASK_AREA_SIZE) rc = DRV_USR_SIZE_TOO_LONG;
  else if (pvData == NULL) rc = DRV_USR_BUF_PTR_NULL;
  else {
    if (copy == READ_STATE) offset = usNumber == 1 ? OFS_TASK1_STATE : OFS_TASK2_STATE;
    else offset = usNumber == 1 ? OFS_TASK1_PARAMETER : OFS_TASK2_PARAMETER;
    if (copy == WRITE_PARAMETER) {
      memcpy(b->mm + offset, pvData, usSize);
      cifemu_bell_ring(&b->bell); /* [ours] the connection bits take effect when rung */
    } else {
      memcpy(pvData, b->mm + offset, usSize);
    }
  }
  cifemu_board_leave(b);
  return rc;
}

CIF_API short DevGetTaskState(unsigned short usDevNumber, unsigned short usNumber,
                              unsigned short usSize, void *pvData) {
  return task_area(usDevNumber, usNumber, usSize, pvData, READ_STATE);
}

CIF_API short DevGetTaskParameter(unsigned short usDevNumber, unsigned short usNumber,
                                  unsigned short usSize, void *pvData) {
  return task_area(usDevNumber, usNumber, usSize, pvData, READ_PARAMETER);
}

/* Takes effect at the next warm start. [ours] tasks 3..7 get -36: a CANopen card has
   parameter areas for tasks 1 and 2 only. */
CIF_API short DevPutTaskParameter(unsigned short usDevNumber, unsigned short usNumber,
                                  unsigned short usSize, void *pvData) {
  return task_area(usDevNumber, usNumber, usSize, pvData, WRITE_PARAMETER);
}

static short read_write(cifemu_board *b, unsigned short usMode, unsigned start,
                        unsigned short usSize, void *pvData) {
  if (usSize && pvData == NULL) return DRV_USR_BUF_PTR_NULL;
  if (usSize == 0) return DRV_NO_ERROR;
  if (usMode == PARAMETER_READ) {
    memcpy(pvData, b->mm + start, usSize);
  } else {
    memcpy(b->mm + start, pvData, usSize);
    cifemu_bell_ring(&b->bell);
  }
  return DRV_NO_ERROR;
}

CIF_API short DevReadWriteDPMRaw(unsigned short usDevNumber, unsigned short usMode,
                                 unsigned short usOffset, unsigned short usSize, void *pvData) {
  short rc;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  if (b == NULL) return rc;
  if (usMode != PARAMETER_READ && usMode != PARAMETER_WRITE) rc = DRV_USR_MODE_INVALID;
  else if ((unsigned)usOffset + usSize > RAW_AREA_LIMIT) rc = DRV_USR_SIZE_TOO_LONG;
  else rc = read_write(b, usMode, LAST_KB + usOffset, usSize, pvData);
  cifemu_board_leave(b);
  return rc;
}

/* Offsets from the image's start; the whole image is reachable (docs/libcif.md). */
CIF_API short DevReadWriteDPMData(unsigned short usDevNumber, unsigned short usMode,
                                  unsigned short usOffset, unsigned short usSize, void *pvData) {
  short rc;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  if (b == NULL) return rc;
  if (usMode != PARAMETER_READ && usMode != PARAMETER_WRITE) rc = DRV_USR_MODE_INVALID;
  else if ((unsigned)usOffset + usSize > DPM_SIZE) rc = DRV_USR_SIZE_TOO_LONG;
  else rc = read_write(b, usMode, usOffset, usSize, pvData);
  cifemu_board_leave(b);
  return rc;
}

/* [ours] the extended data areas belong to other protocols' cards; the CANopen master
   has none, so every mode is refused with -37 once the board checks passed. */
CIF_API short DevExtendedData(unsigned short usDevNumber, unsigned short usMode,
                              unsigned short usSize, void *pvData) {
  short rc;
  cifemu_board *b = cifemu_board_enter(usDevNumber, &rc);
  (void)usMode;
  (void)usSize;
  (void)pvData;
  if (b == NULL) return rc;
  cifemu_board_leave(b);
  return DRV_USR_MODE_INVALID;
}
