/*
 * legacy_lifecycle.c - a legacy host's shutdown and daemon start through /dev/cif, as
 * the Hilscher API object reaches the card (open, one ioctl per function, packed
 * DEVIO structures in the program's ABI; see legacy_ioctl.c).
 *
 *   legacy_lifecycle exit_while_waiting
 *       Thread A waits in GETMSG (4 s); thread B calls EXITDRV once A sleeps in it.
 *       The program must not crash; A's call ends with the driver's code.
 *   legacy_lifecycle fork_while_waiting
 *       As above, but a child forked meanwhile calls EXITDRV: it has no call in flight,
 *       so the board is unmapped in the child at once (the parent keeps it).
 *   legacy_lifecycle close_all close|close_table|closefrom|raw SCRATCH
 *       After INITDRV and a message round trip the program closes its descriptors the
 *       way daemons do (close() for 3..255 or for the whole table, glibc's
 *       closefrom(3), or raw close system calls for every open descriptor), opens
 *       SCRATCH (onto every number it had open before, for `raw`: dup3 by system
 *       call, as a program's own descriptors would land there), opens /dev/cif again
 *       and talks to the card.
 *       SCRATCH must stay byte for byte as it was, and its descriptors open.
 *   legacy_lifecycle close_ledger SCRATCH
 *       The window a close-all loop leaves inside a call: while thread A waits in GETMSG
 *       (so no call starts with the preload's check of its descriptors), the program
 *       closes the transaction ledger's descriptor with a raw system call and its own
 *       SCRATCH lands on that number (dup3 by system call). Its PUTMSG then writes the
 *       ledger (libcif/src/chanlock.c: through its map; a rewrite is a pwrite) and A
 *       reads the answer (the ledger again). SCRATCH must stay as it was, and the card must go on working.
 *
 * Prints one "name=value" line per step; tests/test_legacy.py compares them.
 */
#define _GNU_SOURCE
#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/sysmacros.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#define COMM_ERR (-33)
#define MAX_FDS 1024

#pragma pack(push, 1)
typedef struct { unsigned char rx, tx, ln, nr, a, f, b, e, data[255], dummy[25]; } msg_t;
typedef struct { unsigned short board, mode; unsigned long timeout, dpm_size; short error; } reset_cmd;
typedef struct { unsigned short board; msg_t msg; unsigned long timeout; short error; } putmsg_cmd;
typedef struct { unsigned short board; unsigned long timeout, size; msg_t msg; short error; } getmsg_cmd;
typedef struct { unsigned char board; unsigned short dev, host; short error; } mbxinfo_cmd;
typedef struct { unsigned short board, count; short error; } exit_cmd;
#pragma pack(pop)

/* driver 2.6's numbers */
#define INITDRV _IOWR('c', 2, char[13])
#define PUTMSG _IO('c', 5)
#define GETMSG _IO('c', 6)
#define MBXINFO _IO('c', 8)
#define EXITDRV _IO('c', 11)

#define SHOW(name, value) printf("%s=%d\n", name, (int)(value))

/* As the API object: ioctl's 0 is a failed call, anything else hands over sError. */
static short call(int fd, unsigned long request, void *cmd, const short *error) {
  int done = ioctl(fd, request, cmd);
  return done == 0 ? COMM_ERR : done < 0 ? (short)-1000 - errno : *error;
}

static short init_board(int fd) {
  reset_cmd c;
  memset(&c, 0, sizeof c);
  return call(fd, INITDRV, &c, &c.error);
}

static short exit_board(int fd) {
  exit_cmd c;
  memset(&c, 0, sizeof c);
  return call(fd, EXITDRV, &c, &c.error);
}

static short put_msg(int fd, const msg_t *msg, unsigned long timeout) {
  putmsg_cmd c;
  memset(&c, 0, sizeof c);
  c.msg = *msg;
  c.timeout = timeout;
  return call(fd, PUTMSG, &c, &c.error);
}

static short get_msg(int fd, msg_t *msg, unsigned long timeout) {
  getmsg_cmd c;
  short rc;
  memset(&c, 0, sizeof c);
  c.timeout = timeout;
  c.size = sizeof c.msg;
  rc = call(fd, GETMSG, &c, &c.error);
  *msg = c.msg;
  return rc;
}

static short mbx_info(int fd) {
  mbxinfo_cmd c;
  memset(&c, 0, sizeof c);
  return call(fd, MBXINFO, &c, &c.error);
}

/* A request the card answers at once (legacy_ioctl.c's round trip). */
static short round_trip(int fd) {
  msg_t msg;
  short rc;
  memset(&msg, 0, sizeof msg);
  msg.rx = 2;
  msg.tx = 16;
  msg.ln = 8;
  msg.nr = 1;
  msg.b = 17;
  msg.data[1] = 1;
  msg.data[2] = 200;
  msg.data[5] = 2;
  msg.data[6] = 5;
  msg.data[7] = 1;
  rc = put_msg(fd, &msg, 1000);
  if (rc != 0) return rc;
  memset(&msg, 0, sizeof msg);
  rc = get_msg(fd, &msg, 2000);
  return rc != 0 ? rc : msg.a == 17 && msg.nr == 1 ? 0 : 1;
}

static long long now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (long long)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

/* Whether the board's image is mapped into this process. */
static int image_mapped(void) {
  char line[512];
  int found = 0;
  FILE *maps = fopen("/proc/self/maps", "r");
  if (maps == NULL) return -1;
  while (fgets(line, sizeof line, maps) != NULL)
    if (strstr(line, "/board0.dpm") != NULL) found = 1;
  fclose(maps);
  return found;
}

/* ---- exit_while_waiting ---------------------------------------------------------------- */

static int device;
static volatile int waiter_tid, waiter_done;
static short waiter_rc;
static unsigned long waiter_timeout = 4000;
static msg_t waiter_msg;

static void *waiter(void *unused) {
  (void)unused;
  __atomic_store_n(&waiter_tid, (int)syscall(SYS_gettid), __ATOMIC_RELEASE);
  waiter_rc = get_msg(device, &waiter_msg, waiter_timeout);
  __atomic_store_n(&waiter_done, 1, __ATOMIC_RELEASE);
  return NULL;
}

/* The waiter's thread sleeps (state S): it is inside GETMSG's wait. */
static int waiter_sleeps(void) {
  char path[64], text[256], *state;
  FILE *f;
  size_t got;
  snprintf(path, sizeof path, "/proc/self/task/%d/stat", __atomic_load_n(&waiter_tid, __ATOMIC_ACQUIRE));
  f = fopen(path, "r");
  if (f == NULL) return 0;
  got = fread(text, 1, sizeof text - 1, f);
  fclose(f);
  text[got] = '\0';
  state = strrchr(text, ')');
  return state != NULL && state[1] == ' ' && state[2] == 'S';
}

static int exit_while_waiting(void) {
  pthread_t thread;
  long long start, deadline;
  int sleeping = 0;
  device = open("/dev/cif", O_RDWR);
  SHOW("open", device >= 0);
  SHOW("initdrv", init_board(device));
  if (pthread_create(&thread, NULL, waiter, NULL) != 0) return 1;
  deadline = now_ms() + 3000;
  while (now_ms() < deadline && !sleeping) {
    sleeping = __atomic_load_n(&waiter_tid, __ATOMIC_ACQUIRE) != 0 && waiter_sleeps();
    if (!sleeping) sched_yield();
  }
  SHOW("waiter_sleeps", sleeping);
  start = now_ms();
  SHOW("exitdrv", exit_board(device));
  /* EXITDRV does not wait for the calls in flight */
  SHOW("exitdrv_returned_at_once", now_ms() - start < 1000);
  SHOW("waiter_still_waiting", !__atomic_load_n(&waiter_done, __ATOMIC_ACQUIRE));
  /* a call that starts after EXITDRV finds the board closed: the driver's -1 */
  {
    msg_t msg;
    memset(&msg, 0, sizeof msg);
    SHOW("putmsg_after_exit", put_msg(device, &msg, 0));
  }
  pthread_join(thread, NULL);
  SHOW("waiter", waiter_rc);
  SHOW("mapped_after_waiter", image_mapped());
  /* the board opens again, and works */
  SHOW("initdrv_again", init_board(device));
  SHOW("round_trip", round_trip(device));
  SHOW("exitdrv_again", exit_board(device));
  SHOW("close", close(device));
  return 0;
}

/* A child forked while another thread of the parent waits in GETMSG: the child has no
   call in flight, so its EXITDRV unmaps the board at once. */
static int fork_while_waiting(void) {
  pthread_t thread;
  long long deadline;
  int sleeping = 0, status = -1;
  pid_t child;
  device = open("/dev/cif", O_RDWR);
  SHOW("open", device >= 0);
  SHOW("initdrv", init_board(device));
  if (pthread_create(&thread, NULL, waiter, NULL) != 0) return 1;
  deadline = now_ms() + 3000;
  while (now_ms() < deadline && !sleeping) {
    sleeping = __atomic_load_n(&waiter_tid, __ATOMIC_ACQUIRE) != 0 && waiter_sleeps();
    if (!sleeping) sched_yield();
  }
  SHOW("waiter_sleeps", sleeping);
  child = fork();
  if (child == 0) {
    SHOW("child_exitdrv", exit_board(device));
    SHOW("child_mapped_after_exitdrv", image_mapped());
    _exit(0);
  }
  waitpid(child, &status, 0);
  SHOW("child_status", status);
  SHOW("parent_mapped", image_mapped());
  pthread_join(thread, NULL);
  SHOW("waiter", waiter_rc);
  SHOW("exitdrv", exit_board(device));
  SHOW("close", close(device));
  return 0;
}

/* ---- close_all ---------------------------------------------------------------------------- */

static int open_descriptors(int *fds) {
  int count = 0;
  DIR *dir = opendir("/proc/self/fd");
  struct dirent *entry;
  if (dir == NULL) return 0;
  while ((entry = readdir(dir)) != NULL && count < MAX_FDS) {
    int fd = atoi(entry->d_name);
    if (entry->d_name[0] != '.' && fd > 2 && fd != dirfd(dir)) fds[count++] = fd;
  }
  closedir(dir);
  return count;
}

static int same_file(int fd, const struct stat *want) {
  struct stat st;
  return fstat(fd, &st) == 0 && st.st_dev == want->st_dev && st.st_ino == want->st_ino;
}

static int read_file(const char *path, unsigned char *data, size_t size) {
  FILE *f = fopen(path, "rb");
  size_t got;
  if (f == NULL) return -1;
  got = fread(data, 1, size, f);
  fclose(f);
  return (int)got;
}

static int close_all(const char *how, const char *scratch) {
  static int before[MAX_FDS], scratch_fds[MAX_FDS];
  unsigned char original[4096], now[4096];
  int count, scratch_count = 0, original_size, i, fd, unchanged, all_open = 1;
  struct stat scratch_st;

  original_size = read_file(scratch, original, sizeof original);
  fd = open("/dev/cif", O_RDONLY);
  SHOW("open", fd >= 0);
  SHOW("initdrv", init_board(fd));
  SHOW("round_trip", round_trip(fd));
  SHOW("mbxinfo", mbx_info(fd));
  count = open_descriptors(before);

  if (strcmp(how, "close") == 0) {
    for (i = 3; i < 256; i++) close(i);
  } else if (strcmp(how, "close_table") == 0) { /* the whole table, as getdtablesize() says */
    int size = getdtablesize() < 65536 ? getdtablesize() : 65536;
    for (i = 3; i < size; i++) close(i);
  } else if (strcmp(how, "closefrom") == 0) {
    closefrom(3);
  } else {
    for (i = 0; i < count; i++) syscall(SYS_close, before[i]);
  }
  /* the program's own files take the numbers that were free */
  for (i = 0; i < count; i++) {
    int scratch_fd = open(scratch, O_RDWR | O_APPEND);
    if (scratch_fd < 0) return 1;
    scratch_fds[scratch_count++] = scratch_fd;
    if (strcmp(how, "raw") == 0 && scratch_fd != before[i]) {
      /* as a descriptor the program got from the kernel without libc's open */
      if (syscall(SYS_dup3, scratch_fd, before[i], O_CLOEXEC) < 0) return 1;
      scratch_fds[scratch_count++] = before[i];
    }
  }
  fstat(scratch_fds[0], &scratch_st);

  fd = open("/dev/cif", O_RDONLY);
  SHOW("reopen", fd >= 0);
  SHOW("mbxinfo_after", mbx_info(fd));
  SHOW("round_trip_after", round_trip(fd));
  SHOW("exitdrv", exit_board(fd));
  SHOW("close", close(fd));

  for (i = 0; i < scratch_count; i++) all_open &= same_file(scratch_fds[i], &scratch_st);
  SHOW("scratch_fds_open", all_open);
  unchanged = read_file(scratch, now, sizeof now) == original_size &&
              memcmp(now, original, (size_t)original_size) == 0;
  SHOW("scratch_unchanged", unchanged);
  return 0;
}

/* ---- close_ledger ------------------------------------------------------------------------- */

/* The descriptor whose file's path ends with `suffix`, or -1; its path in `path`. */
static int find_fd(const char *suffix, char *path, size_t size) {
  int fds[MAX_FDS], count = open_descriptors(fds), i;
  for (i = 0; i < count; i++) {
    char link[64];
    ssize_t got;
    snprintf(link, sizeof link, "/proc/self/fd/%d", fds[i]);
    got = readlink(link, path, size - 1);
    if (got <= 0) continue;
    path[got] = '\0';
    if (got >= (ssize_t)strlen(suffix) && strcmp(path + got - strlen(suffix), suffix) == 0)
      return fds[i];
  }
  return -1;
}

/* Whether this process holds an flock on the file at `path` (/proc/locks). */
static int flocked_here(const char *path) {
  char line[256], want[96];
  struct stat st;
  FILE *locks;
  int found = 0;
  if (stat(path, &st) != 0 || (locks = fopen("/proc/locks", "r")) == NULL) return 0;
  snprintf(want, sizeof want, " %ld %02x:%02x:%lu ", (long)getpid(), major(st.st_dev),
           minor(st.st_dev), (unsigned long)st.st_ino);
  while (!found && fgets(line, sizeof line, locks) != NULL)
    found = strstr(line, "FLOCK") != NULL && strstr(line, "->") == NULL &&
            strstr(line, want) != NULL;
  fclose(locks);
  return found;
}

static int close_ledger(const char *scratch) {
  unsigned char original[4096], now[4096];
  char txn_lock[4096], ledger_path[4096];
  int original_size, ledger, scratch_fd, moved = -1, inside = 0;
  struct stat scratch_st;
  pthread_t thread;
  long long deadline;
  msg_t msg;

  original_size = read_file(scratch, original, sizeof original);
  device = open("/dev/cif", O_RDWR);
  SHOW("open", device >= 0);
  SHOW("initdrv", init_board(device));
  SHOW("round_trip", round_trip(device));
  /* A waits in GETMSG until the answer to the PUTMSG below comes */
  waiter_timeout = 20000;
  /* the round trip above let the transaction lock go: the waiter's GETMSG takes it */
  if (find_fd("/board0.transaction.lock", txn_lock, sizeof txn_lock) < 0) return 1;
  if (pthread_create(&thread, NULL, waiter, NULL) != 0) return 1;
  deadline = now_ms() + 10000;
  while (now_ms() < deadline && !(inside = flocked_here(txn_lock))) sched_yield();
  SHOW("waiter_inside", inside);

  ledger = find_fd("/board0.transaction.lock", ledger_path, sizeof ledger_path);
  SHOW("ledger_found", ledger >= 0);
  syscall(SYS_close, ledger);
  scratch_fd = open(scratch, O_RDWR);
  if (scratch_fd >= 0 && scratch_fd != ledger)
    moved = (int)syscall(SYS_dup3, scratch_fd, ledger, O_CLOEXEC);
  SHOW("scratch_on_ledger_number", moved == ledger || scratch_fd == ledger);
  fstat(scratch_fd, &scratch_st);

  memset(&msg, 0, sizeof msg); /* round_trip's request: a shared-memory read */
  msg.rx = 2;
  msg.tx = 16;
  msg.ln = 8;
  msg.nr = 1;
  msg.b = 17;
  msg.data[1] = 1;
  msg.data[2] = 200;
  msg.data[5] = 2;
  msg.data[6] = 5;
  msg.data[7] = 1;
  SHOW("putmsg", put_msg(device, &msg, 1000));
  pthread_join(thread, NULL);
  SHOW("waiter", waiter_rc);
  SHOW("waiter_read_the_answer", waiter_msg.a == 17 && waiter_msg.nr == 1);
  SHOW("round_trip_after", round_trip(device));
  SHOW("exitdrv", exit_board(device));
  SHOW("close", close(device));

  SHOW("scratch_fds_open", same_file(scratch_fd, &scratch_st) && same_file(ledger, &scratch_st));
  SHOW("scratch_unchanged", read_file(scratch, now, sizeof now) == original_size &&
                                memcmp(now, original, (size_t)original_size) == 0);
  return 0;
}

int main(int argc, char **argv) {
  setvbuf(stdout, NULL, _IONBF, 0);
  if (argc == 2 && strcmp(argv[1], "exit_while_waiting") == 0) return exit_while_waiting();
  if (argc == 2 && strcmp(argv[1], "fork_while_waiting") == 0) return fork_while_waiting();
  if (argc == 4 && strcmp(argv[1], "close_all") == 0) return close_all(argv[2], argv[3]);
  if (argc == 3 && strcmp(argv[1], "close_ledger") == 0) return close_ledger(argv[2]);
  fprintf(stderr, "usage: legacy_lifecycle exit_while_waiting | fork_while_waiting | "
                  "close_all HOW SCRATCH | close_ledger SCRATCH\n");
  return 2;
}
