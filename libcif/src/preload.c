/*
 * preload.c - the /dev/cif character device for unchanged legacy binaries (LD_PRELOAD).
 *
 * A legacy program has Hilscher's API object linked in; that object reaches the card
 * only through open("/dev/cif") and one ioctl per driver function, with a packed
 * DEVIO_* structure whose last field sError the driver fills in. Loaded with
 * LD_PRELOAD, this library answers those calls from the emulated card's image, with
 * libcif's implementation underneath, and hands every other file to libc.
 *
 * What the kernel driver did is the model (both generations, 2.100 and 2.6, behave
 * alike; they differ only in the numbers of five ioctls, and both are accepted):
 * - the structures have the program's own ABI: they are declared here with native
 *   `unsigned long` and pointers, so the i386 build reads i386 programs' structures
 *   and the x86-64 build x86-64 programs';
 * - ioctl's return value is the driver's: the byte count it reported, 0 where it
 *   reported nothing (the API object then returns DRV_USR_COMM_ERR, -33), and -1 with
 *   errno where the driver returned a negative value;
 * - sError is the driver's code: -1 (DRV_BOARD_NOT_INITIALIZED) for a board that is
 *   not there or not initialised, the device codes (-11, -4, -16 ... -24) as libcif
 *   gives them; structures the driver never wrote back stay untouched.
 * Where the driver copied unchecked lengths or pointers (it would have overrun kernel
 * memory or failed silently), the preload refuses with the API object's code [ours]:
 * -43 for a length beyond the area, -46/-47 for the I/O area, -45 (-48/-49 for the
 * exchange buffers) for a pointer it cannot read or write; a structure it cannot read
 * at all fails with EFAULT. Every user pointer is read and written through a pipe, so
 * a bad one gives EFAULT from the kernel instead of a crash.
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#undef _FORTIFY_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <poll.h>
#include <pthread.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/types.h>
#include <unistd.h>

#include "cif_user.h"
#include "dpm.h"

#define DEVICE_PATH "/dev/cif"
#define DEFAULT_DPM_DIR "/dev/shm/cif" /* libcif's default as well */
#define MAX_DEVICE_FDS 64
#define DRV_BOARD_NOT_INIT (-1) /* DRV_BOARD_NOT_INITIALIZED: the driver's own code */
#define DRV_PARAM_UNKNOWN (-5)  /* DRV_PARAMETER_UNKNOWN */
#define NUMBER_OF_IOCTLS 25

/* ---- the ioctl numbers of both driver generations ----------------------------------- */

#define IOC_MAGIC 'c'
#define IOC_NR(cmd) ((unsigned)(cmd) & 0xFFu)
#define IOC_TYPE(cmd) (((unsigned)(cmd) >> 8) & 0xFFu)
#define IOC_PLAIN(n) (0x6300u | (n))

enum {
  NR_BOARDINFO = 1, NR_INITDRV, NR_PARAMETER, NR_RESETDEV, NR_PUTMSG, NR_GETMSG,
  NR_TASKSTATE, NR_MBXINFO, NR_TRIGGERWD, NR_GETINFO, NR_EXITDRV, NR_GETPARAMETER,
  NR_EXIO, NR_SETHOST, NR_READSEND, NR_EXTDATA, NR_GETMBX, NR_BOARDINFOEX, NR_EXIOEX,
  NR_EXIOERR, NR_RWRAW, NR_SPCONTROL, NR_GETDPMPTR, NR_RWDPMDATA, NR_IRQ_POLL
};

/* The five numbers that carry a size: driver 2.6 encodes the array it names, driver
   2.100 sizeof(int) (docs/legacy.md). */
static unsigned expected_cmd(unsigned nr, int generation_26) {
  switch (nr) {
    case NR_BOARDINFO: return generation_26 ? 0xc1006301u : 0xc0046301u;
    case NR_INITDRV: return generation_26 ? 0xc00d6302u : 0xc0046302u;
    case NR_PARAMETER: return generation_26 ? 0x40476303u : 0x40046303u;
    case NR_RESETDEV: return generation_26 ? 0x400d6304u : 0x40046304u;
    case NR_IRQ_POLL: return generation_26 ? 0xc00d6319u : 0xc0046319u;
    default: return IOC_PLAIN(nr);
  }
}

/* ---- the DEVIO_* structures, in the program's ABI ----------------------------------- */

typedef unsigned long native_ul; /* the driver header's `unsigned long` */

#pragma pack(push, 1)
typedef struct { uint16_t board, mode, irq; int16_t error; } io_opmode;
typedef struct { uint16_t board, length; void *info; int16_t error; } io_boardinfo;
typedef struct { uint16_t board, mode; native_ul timeout, dpm_size; int16_t error; } io_reset;
typedef struct { uint16_t board, number, length; uint8_t data[64]; int16_t error; } io_param;
typedef struct { uint16_t board; MSG_STRUC msg; native_ul timeout; int16_t error; } io_putmsg;
typedef struct {
  uint16_t board;
  native_ul timeout, size;
  MSG_STRUC msg;
  int16_t error;
} io_getmsg;
typedef struct { uint8_t board; uint16_t number, length; uint8_t data[64]; int16_t error; } io_taskstate;
typedef struct { uint8_t board; uint16_t dev_state, host_state; int16_t error; } io_mbxinfo;
typedef struct { uint16_t board, mode; native_ul timeout; uint16_t value; int16_t error; } io_trigger;
typedef struct { uint16_t board, area, length; void *data; int16_t error; } io_getinfo;
typedef struct { uint16_t board, open_count; int16_t error; } io_exit;
typedef struct {
  uint16_t board, send_offset, send_length;
  void *send;
  uint16_t receive_offset, receive_length;
  void *receive;
  native_ul timeout;
  int16_t error;
} io_exio;
typedef struct { io_exio io; uint16_t mode; } io_exioex;
typedef struct { io_exio io; void *state; } io_exioerr;
typedef struct { uint16_t board, offset, length; void *data; int16_t error; } io_readsend;
typedef struct { uint16_t board, mode; void *data; int16_t error; } io_extdata;
typedef struct {
  uint16_t board, dev_length, host_length;
  uint8_t host[MSG_BUFFER_SIZE], dev[MSG_BUFFER_SIZE];
  int16_t error;
} io_getmbx;
typedef struct { uint16_t board, mode, offset, length; void *data; int16_t error; } io_rawdata;

/* The driver's information structures with native `unsigned long` fields. */
typedef struct {
  char version[16];
  struct { uint16_t board, available; native_ul address; uint16_t irq; } entry[MAX_DEV_BOARDS];
  uint16_t detected;
} drv_boardinfo;
typedef struct {
  native_ul open, close, read, write, irq;
  uint8_t flags[9]; /* InitMsgFlag ... ExComBit, as DRIVERINFO orders them */
  native_ul exio;
} drv_driverinfo;
typedef struct { uint8_t com, mode; native_ul count; } drv_ioinfo;
typedef struct { native_ul date, device, serial, reserved; uint8_t names[16]; } drv_versioninfo;
typedef struct {
  char version[16];
  struct {
    uint16_t board, available;
    native_ul address;
    uint16_t irq;
    drv_driverinfo driver;
    FIRMWAREINFO firmware;
    DEVINFO device;
    RCSINFO rcs;
    drv_versioninfo version;
  } entry[MAX_DEV_BOARDS];
} drv_boardinfoex;
#pragma pack(pop)

#define ASSERT_SIZE(type, size) _Static_assert(sizeof(type) == (size), #type)
#if defined(__x86_64__)
#define UL 8
#define PTR 8
#else
#define UL 4
#define PTR 4
#endif
ASSERT_SIZE(io_opmode, 8);
ASSERT_SIZE(io_boardinfo, 6 + PTR);
ASSERT_SIZE(io_reset, 6 + 2 * UL);
ASSERT_SIZE(io_param, 72);
ASSERT_SIZE(io_putmsg, 292 + UL);
ASSERT_SIZE(io_getmsg, 292 + 2 * UL);
ASSERT_SIZE(io_taskstate, 71);
ASSERT_SIZE(io_mbxinfo, 7);
ASSERT_SIZE(io_trigger, 8 + UL);
ASSERT_SIZE(io_getinfo, 8 + PTR);
ASSERT_SIZE(io_exit, 6);
ASSERT_SIZE(io_exio, 12 + 2 * PTR + UL);
ASSERT_SIZE(io_exioex, 14 + 2 * PTR + UL);
ASSERT_SIZE(io_exioerr, 12 + 3 * PTR + UL);
ASSERT_SIZE(io_readsend, 8 + PTR);
ASSERT_SIZE(io_extdata, 6 + PTR);
ASSERT_SIZE(io_getmbx, 584);
ASSERT_SIZE(io_rawdata, 10 + PTR);
ASSERT_SIZE(drv_boardinfo, 18 + 4 * (6 + UL));
ASSERT_SIZE(drv_driverinfo, 9 + 6 * UL);
ASSERT_SIZE(drv_ioinfo, 2 + UL);
ASSERT_SIZE(drv_versioninfo, 16 + 4 * UL);
ASSERT_SIZE(drv_boardinfoex, 16 + 4 * (6 + UL + 9 + 6 * UL + 32 + 6 + 8 + 16 + 4 * UL));

/* ---- libc underneath ------------------------------------------------------------------ */

typedef int (*open_fn)(const char *, int, ...);
typedef int (*openat_fn)(int, const char *, int, ...);
typedef int (*close_fn)(int);
typedef int (*ioctl_fn)(int, unsigned long, ...);
typedef int (*fcntl_fn)(int, int, ...);

static void *next_symbol(const char *name) { return dlsym(RTLD_NEXT, name); }

/* The libc function the program would have reached (open for open, open64 for open64:
   an i386 program without large-file support keeps its flags); direct system calls
   when dlsym has none. */
static int real_open_named(const char *name, const char *path, int flags, mode_t mode) {
  static open_fn open_fn_cache, open64_fn_cache;
  open_fn *cache = strcmp(name, "open") == 0 ? &open_fn_cache : &open64_fn_cache;
  open_fn fn = __atomic_load_n(cache, __ATOMIC_ACQUIRE);
  if (fn == NULL) {
    fn = (open_fn)next_symbol(name);
    __atomic_store_n(cache, fn, __ATOMIC_RELEASE);
  }
  if (fn == NULL) return (int)syscall(SYS_openat, AT_FDCWD, path, flags, mode);
  return fn(path, flags, mode);
}
static int real_open(const char *path, int flags, mode_t mode) {
  return real_open_named("open", path, flags, mode);
}
static int real_openat_named(const char *name, int dirfd, const char *path, int flags,
                             mode_t mode) {
  static openat_fn openat_fn_cache, openat64_fn_cache;
  openat_fn *cache = strcmp(name, "openat") == 0 ? &openat_fn_cache : &openat64_fn_cache;
  openat_fn fn = __atomic_load_n(cache, __ATOMIC_ACQUIRE);
  if (fn == NULL) {
    fn = (openat_fn)next_symbol(name);
    __atomic_store_n(cache, fn, __ATOMIC_RELEASE);
  }
  if (fn == NULL) return (int)syscall(SYS_openat, dirfd, path, flags, mode);
  return fn(dirfd, path, flags, mode);
}
static int real_close(int fd) {
  static close_fn fn;
  if (fn == NULL) fn = (close_fn)next_symbol("close");
  if (fn == NULL) return (int)syscall(SYS_close, fd);
  return fn(fd);
}
static int real_ioctl(int fd, unsigned long request, void *arg) {
  static ioctl_fn fn;
  if (fn == NULL) fn = (ioctl_fn)next_symbol("ioctl");
  if (fn == NULL) return (int)syscall(SYS_ioctl, fd, request, arg);
  return fn(fd, request, arg);
}
static int real_fcntl(int fd, int cmd, void *arg) {
  static fcntl_fn fn;
  if (fn == NULL) fn = (fcntl_fn)next_symbol("fcntl");
  if (fn == NULL) return (int)syscall(SYS_fcntl, fd, cmd, arg);
  return fn(fd, cmd, arg);
}

/* ---- the preload's own descriptors [ours] ------------------------------------------------

   The kernel driver had no descriptors in the program; the preload has some: the copy
   pipe, and libcif's board files (the lock files, the doorbell socket, the image
   directory, an image while it is mapped). Daemons close every descriptor they do not
   know and then open their own files onto the freed numbers. So each of the preload's
   descriptors
   - lives at the top of the descriptor table (F_DUPFD_CLOEXEC from PRIVATE_TOP below
     min(RLIMIT_NOFILE, 1024)), where a program's lowest-free allocation comes last;
   - is not closed by the program's close, close_range or closefrom (close answers
     EBADF: for the program nothing is open there);
   - is checked before every use: fstat's st_dev/st_ino must be those it had when the
     preload opened it. One that was closed or replaced behind libc's back (a raw
     system call, dup2 onto it) is stale: never read, written, locked or closed again;
     the preload opens a new one (the pipe at once, a board at the next ioctl that
     finds no other call in flight, see board_maintenance).
   libcif's calls reach these through the linker's --wrap (libcif/Makefile), so libcif's
   sources stay as they are: every call libcif makes on a descriptor (open, socket, bind,
   close, dup2, fcntl, flock, sendto, recv, poll, fstat, mmap, pread, pwrite)
   checks it first and answers EBADF for a stale one, so that a ledger line or a lock
   never goes into a program's file that took the number. The preload's own fstat calls
   below go to libc's (__real_fstat): they are the check. */

#define PRIVATE_TOP 64     /* slots kept at the top of the table */
#define MAX_PRIVATE_FDS 128

typedef struct { int fd, stale; dev_t dev; ino_t ino; } private_fd;

int __real_fstat(int fd, struct stat *st);

static pthread_mutex_t private_lock = PTHREAD_MUTEX_INITIALIZER;
static private_fd private_fds[MAX_PRIVATE_FDS];
static int private_count;
static int private_used; /* the program's close checks the table from the first one on */

/* A number can have a stale entry (libcif's, until DevExitBoard) and a fresh one (the
   number was free again and the preload took it): the fresh one is the descriptor. */
static private_fd *private_find_locked(int fd) {
  private_fd *stale = NULL;
  int i;
  for (i = 0; i < private_count; i++) {
    if (private_fds[i].fd != fd) continue;
    if (!private_fds[i].stale) return &private_fds[i];
    stale = &private_fds[i];
  }
  return stale;
}

static void private_remove_locked(private_fd *entry) {
  *entry = private_fds[--private_count];
}

/* The entry still names the file the preload opened; a stale one never again. */
static int private_valid_locked(private_fd *entry) {
  struct stat st;
  if (entry->stale) return 0;
  if (__real_fstat(entry->fd, &st) != 0 || st.st_dev != entry->dev || st.st_ino != entry->ino)
    entry->stale = 1;
  return !entry->stale;
}

/* A new descriptor of the preload's: moved to the top of the table and registered.
   -1 (EMFILE) when the table is full: a descriptor it cannot check is not kept. */
static int private_adopt_locked(int fd) {
  struct rlimit limit;
  struct stat st;
  int floor = 0, moved;
  if (fd < 0) return fd;
  if (getrlimit(RLIMIT_NOFILE, &limit) == 0) {
    rlim_t top = limit.rlim_cur < 1024 ? limit.rlim_cur : 1024;
    if (top > 2 * PRIVATE_TOP) floor = (int)(top - PRIVATE_TOP);
  }
  if (floor > fd) {
    moved = (int)syscall(SYS_fcntl, fd, F_DUPFD_CLOEXEC, floor);
    if (moved >= 0) {
      syscall(SYS_close, fd);
      fd = moved;
    }
  }
  if (private_count == MAX_PRIVATE_FDS || __real_fstat(fd, &st) != 0) {
    syscall(SYS_close, fd);
    errno = EMFILE;
    return -1;
  }
  private_fds[private_count].fd = fd;
  private_fds[private_count].stale = 0;
  private_fds[private_count].dev = st.st_dev;
  private_fds[private_count].ino = st.st_ino;
  private_count++;
  return fd;
}

/* Whether fd is one of the preload's and still its own file: the check before a use. */
static int private_verified(int fd) {
  private_fd *entry;
  int valid;
  pthread_mutex_lock(&private_lock);
  entry = private_find_locked(fd);
  valid = entry != NULL && private_valid_locked(entry);
  pthread_mutex_unlock(&private_lock);
  return valid;
}

/* Close one of the preload's descriptors; a stale one is only forgotten (the number is
   the program's now). Anything else is not the preload's to close: EBADF. */
static int private_close(int fd) {
  private_fd *entry;
  int rc = -1;
  pthread_mutex_lock(&private_lock);
  entry = private_find_locked(fd);
  if (entry != NULL) {
    if (private_valid_locked(entry)) rc = (int)syscall(SYS_close, fd);
    else rc = 0;
    private_remove_locked(entry);
  }
  pthread_mutex_unlock(&private_lock);
  if (entry == NULL) errno = EBADF;
  return rc;
}

/* Check every registered descriptor now; 1 when one is stale. The stale entries stay
   until their owner closes them (libcif in DevExitBoard) or private_purge_stale. */
static int private_any_stale(void) {
  int i, stale = 0;
  pthread_mutex_lock(&private_lock);
  for (i = 0; i < private_count; i++) stale |= !private_valid_locked(&private_fds[i]);
  pthread_mutex_unlock(&private_lock);
  return stale;
}

static void private_purge_stale(void) {
  int i;
  pthread_mutex_lock(&private_lock);
  for (i = private_count - 1; i >= 0; i--)
    if (private_fds[i].stale) private_remove_locked(&private_fds[i]);
  pthread_mutex_unlock(&private_lock);
}

/* The program's close of fd: 1 when the preload keeps it (its own, still valid). A
   stale entry becomes the program's descriptor to close. */
static int private_refuses_close(int fd) {
  private_fd *entry;
  int keep = 0;
  if (!__atomic_load_n(&private_used, __ATOMIC_ACQUIRE)) return 0;
  pthread_mutex_lock(&private_lock);
  entry = private_find_locked(fd);
  if (entry != NULL) keep = private_valid_locked(entry);
  pthread_mutex_unlock(&private_lock);
  return keep;
}

/* libcif's descriptor calls (-Wl,--wrap in libcif/Makefile). __real_* is libc's. */
int __real_socket(int domain, int type, int protocol);
int __real_bind(int fd, const struct sockaddr *address, socklen_t length);
int __real_flock(int fd, int operation);
void *__real_mmap(void *address, size_t length, int protection, int flags, int fd, off_t offset);
ssize_t __real_pread(int fd, void *buf, size_t count, off_t offset);
ssize_t __real_pwrite(int fd, const void *buf, size_t count, off_t offset);
ssize_t __real_sendto(int fd, const void *buf, size_t len, int flags,
                      const struct sockaddr *to, socklen_t to_len);
ssize_t __real_recv(int fd, void *buf, size_t len, int flags);
int __real_poll(struct pollfd *fds, nfds_t count, int timeout);

int __wrap_open(const char *path, int flags, ...);
int __wrap_socket(int domain, int type, int protocol);
int __wrap_close(int fd);
int __wrap_flock(int fd, int operation);
ssize_t __wrap_sendto(int fd, const void *buf, size_t len, int flags,
                      const struct sockaddr *to, socklen_t to_len);
ssize_t __wrap_recv(int fd, void *buf, size_t len, int flags);
int __wrap_poll(struct pollfd *fds, nfds_t count, int timeout);
int __wrap_bind(int fd, const struct sockaddr *address, socklen_t length);
int __wrap_dup2(int oldfd, int newfd);
int __wrap_fcntl(int fd, int cmd, ...);
int __wrap_fstat(int fd, struct stat *st);
void *__wrap_mmap(void *address, size_t length, int protection, int flags, int fd, off_t offset);
ssize_t __wrap_pread(int fd, void *buf, size_t count, off_t offset);
ssize_t __wrap_pwrite(int fd, const void *buf, size_t count, off_t offset);

/* EBADF unless fd is the preload's and still its own file. */
static int refuse_stale(int fd) {
  if (private_verified(fd)) return 0;
  errno = EBADF;
  return 1;
}

/* Held across libc's open and the move: the program's close of the fresh low number
   waits until it is the preload's at the top (or nobody's). */
int __wrap_open(const char *path, int flags, ...) {
  va_list args;
  mode_t mode = 0;
  int fd;
  va_start(args, flags);
  if (flags & O_CREAT) mode = (mode_t)va_arg(args, int);
  va_end(args);
  pthread_mutex_lock(&private_lock);
  fd = private_adopt_locked(real_open(path, flags | O_CLOEXEC, mode));
  pthread_mutex_unlock(&private_lock);
  return fd;
}

int __wrap_socket(int domain, int type, int protocol) {
  int fd;
  pthread_mutex_lock(&private_lock);
  fd = private_adopt_locked(__real_socket(domain, type | SOCK_CLOEXEC, protocol));
  pthread_mutex_unlock(&private_lock);
  return fd;
}

int __wrap_close(int fd) { return private_close(fd); }

int __wrap_flock(int fd, int operation) {
  return refuse_stale(fd) ? -1 : __real_flock(fd, operation);
}

ssize_t __wrap_sendto(int fd, const void *buf, size_t len, int flags,
                      const struct sockaddr *to, socklen_t to_len) {
  return refuse_stale(fd) ? -1 : __real_sendto(fd, buf, len, flags, to, to_len);
}

ssize_t __wrap_recv(int fd, void *buf, size_t len, int flags) {
  return refuse_stale(fd) ? -1 : __real_recv(fd, buf, len, flags);
}

int __wrap_bind(int fd, const struct sockaddr *address, socklen_t length) {
  return refuse_stale(fd) ? -1 : __real_bind(fd, address, length);
}

int __wrap_fstat(int fd, struct stat *st) {
  return refuse_stale(fd) ? -1 : __real_fstat(fd, st);
}

/* The image's map: a program's file that took the image's number is never mapped. */
void *__wrap_mmap(void *address, size_t length, int protection, int flags, int fd,
                  off_t offset) {
  if (!(flags & MAP_ANONYMOUS) && refuse_stale(fd)) return MAP_FAILED;
  return __real_mmap(address, length, protection, flags, fd, offset);
}

/* The ledger (chanlock.c): read, written and cut only while the lock file is its own. */
ssize_t __wrap_pread(int fd, void *buf, size_t count, off_t offset) {
  return refuse_stale(fd) ? -1 : __real_pread(fd, buf, count, offset);
}

ssize_t __wrap_pwrite(int fd, const void *buf, size_t count, off_t offset) {
  return refuse_stale(fd) ? -1 : __real_pwrite(fd, buf, count, offset);
}

/* A forked child's lock files (cifemu_chanlock_reopen): the new description goes onto the
   lock's number only while that number is still the preload's; the entry then names
   the file the new description is. */
int __wrap_dup2(int oldfd, int newfd) {
  private_fd *from, *to;
  int done = -1;
  pthread_mutex_lock(&private_lock);
  from = private_find_locked(oldfd);
  to = private_find_locked(newfd);
  if (from == NULL || to == NULL || !private_valid_locked(from) || !private_valid_locked(to)) {
    errno = EBADF;
  } else {
    done = (int)syscall(SYS_dup3, oldfd, newfd, O_CLOEXEC);
    if (done >= 0) {
      to->dev = from->dev;
      to->ino = from->ino;
    }
  }
  pthread_mutex_unlock(&private_lock);
  return done;
}

int __wrap_fcntl(int fd, int cmd, ...) {
  va_list args;
  void *arg;
  va_start(args, cmd);
  arg = va_arg(args, void *);
  va_end(args);
  return refuse_stale(fd) ? -1 : real_fcntl(fd, cmd, arg);
}

/* A stale descriptor is left out (fd -1): the wait still lasts its time, as a bell
   that does not ring, and libcif polls the flags. */
int __wrap_poll(struct pollfd *fds, nfds_t count, int timeout) {
  struct pollfd checked[8];
  nfds_t i;
  int done;
  if (count > sizeof checked / sizeof checked[0]) {
    errno = EINVAL;
    return -1;
  }
  for (i = 0; i < count; i++) {
    checked[i] = fds[i];
    if (!private_verified(fds[i].fd)) checked[i].fd = -1;
  }
  done = __real_poll(checked, count, timeout);
  for (i = 0; i < count; i++) fds[i].revents = checked[i].fd < 0 ? 0 : checked[i].revents;
  return done;
}

/* ---- the device's descriptors ----------------------------------------------------------- */

/* state_lock guards the descriptor table; board_lock the driver's and the boards' state.
   Neither is taken while holding the other; private_lock (the preload's own
   descriptors) may be taken under either. */
static pthread_mutex_t state_lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_mutex_t board_lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_mutex_t pipe_lock = PTHREAD_MUTEX_INITIALIZER; /* the copy pipe, below */
static int device_fds[MAX_DEVICE_FDS];
static int device_fd_count;
static dev_t device_dev; /* what a device descriptor is underneath: /dev/null's st_dev/st_ino */
static ino_t device_ino;
static int driver_open;                       /* DevOpenDriver succeeded once */
static unsigned board_opens[MAX_DEV_BOARDS]; /* INITDRV minus EXITDRV, in this process */
static int board_mapped[MAX_DEV_BOARDS];      /* libcif holds the board (DevInitBoard) */
static unsigned calls_in_flight;              /* device ioctls running now, all threads */

static int is_device_path(const char *path) { return path != NULL && strcmp(path, DEVICE_PATH) == 0; }

static void forget_fd_locked(int fd);

/* A device descriptor the program closed behind libc's back (a raw system call) and
   whose number now holds another file is that file, not the device [ours]. */
static int is_device_fd(int fd) {
  int i, found = 0;
  struct stat st;
  /* most calls of most programs: no device open, no lock taken */
  if (fd < 0 || __atomic_load_n(&device_fd_count, __ATOMIC_ACQUIRE) == 0) return 0;
  pthread_mutex_lock(&state_lock);
  for (i = 0; i < device_fd_count && !found; i++) found = device_fds[i] == fd;
  if (found &&
      (__real_fstat(fd, &st) != 0 || st.st_dev != device_dev || st.st_ino != device_ino)) {
    forget_fd_locked(fd);
    found = 0;
  }
  pthread_mutex_unlock(&state_lock);
  return found;
}

/* A descriptor libc just gave the program (open, openat) is not the device. */
static int not_a_device(int fd) {
  if (fd >= 0 && __atomic_load_n(&device_fd_count, __ATOMIC_ACQUIRE) != 0) {
    pthread_mutex_lock(&state_lock);
    forget_fd_locked(fd);
    pthread_mutex_unlock(&state_lock);
  }
  return fd;
}

static void forget_fd_locked(int fd) {
  int i;
  for (i = 0; i < device_fd_count; i++) {
    if (device_fds[i] == fd) {
      device_fds[i] = device_fds[device_fd_count - 1];
      __atomic_store_n(&device_fd_count, device_fd_count - 1, __ATOMIC_RELEASE);
      return;
    }
  }
}

static int remember_fd_locked(int fd) {
  forget_fd_locked(fd);
  if (device_fd_count == MAX_DEVICE_FDS) return -1;
  device_fds[device_fd_count] = fd;
  __atomic_store_n(&device_fd_count, device_fd_count + 1, __ATOMIC_RELEASE);
  return 0;
}

static const char *image_directory(void) {
  const char *env = getenv("CIF_DPM_DIR");
  return env != NULL ? env : DEFAULT_DPM_DIR;
}

/* The board is there: its image exists (the driver: a board it detected at load). */
static int board_exists(unsigned board) {
  char path[PATH_MAX];
  struct stat st;
  if (board >= MAX_DEV_BOARDS) return 0;
  snprintf(path, sizeof path, "%s/board%u.dpm", image_directory(), board);
  return stat(path, &st) == 0 && S_ISREG(st.st_mode);
}

static int any_board(void) {
  unsigned n;
  for (n = 0; n < MAX_DEV_BOARDS; n++)
    if (board_exists(n)) return 1;
  return 0;
}

/* A child of fork has only the thread that forked: none of its device calls is in
   flight, whatever the parent's other threads were doing, and a lock one of them held
   would stay locked (libcif's fork handler, which runs next, opens files through
   __wrap_open and __wrap_dup2). */
static void child_after_fork(void) {
  calls_in_flight = 0;
  pthread_mutex_init(&private_lock, NULL);
  pthread_mutex_init(&state_lock, NULL);
  pthread_mutex_init(&board_lock, NULL);
  pthread_mutex_init(&pipe_lock, NULL);
}
static pthread_once_t forks_watched = PTHREAD_ONCE_INIT;
static void watch_forks(void) { pthread_atfork(NULL, NULL, child_after_fork); }

/* open("/dev/cif"): a descriptor of /dev/null stands for the device, so that fcntl,
   dup, poll and close work on it as on any descriptor. The driver refused the open
   with ENODEV when it had found no board. */
static int device_open(int flags) {
  struct stat st;
  int fd;
  if (!any_board()) {
    errno = ENODEV;
    return -1;
  }
  /* from here on the program's close looks at the preload's own descriptors, before
     libcif or the copy pipe opens the first */
  __atomic_store_n(&private_used, 1, __ATOMIC_RELEASE);
  pthread_once(&forks_watched, watch_forks);
  pthread_mutex_lock(&board_lock);
  if (!driver_open) driver_open = DevOpenDriver() == DRV_NO_ERROR;
  pthread_mutex_unlock(&board_lock);
  if (!driver_open) {
    errno = ENODEV;
    return -1;
  }
  fd = real_open("/dev/null", (flags & (O_ACCMODE | O_CLOEXEC | O_NONBLOCK | O_APPEND)), 0);
  if (fd < 0) return -1;
  pthread_mutex_lock(&state_lock);
  if (__real_fstat(fd, &st) != 0) st.st_ino = 0;
  device_dev = st.st_dev;
  device_ino = st.st_ino;
  if (st.st_ino == 0 || remember_fd_locked(fd) != 0) {
    pthread_mutex_unlock(&state_lock);
    real_close(fd);
    errno = EMFILE;
    return -1;
  }
  pthread_mutex_unlock(&state_lock);
  return fd;
}

/* ---- user memory, read and written without trusting it ---------------------------------- */

static int copy_pipe[2] = {-1, -1};

static void drain(size_t count) {
  unsigned char scratch[512];
  while (count > 0) {
    long got = syscall(SYS_read, copy_pipe[0], scratch, count < sizeof scratch ? count : sizeof scratch);
    if (got <= 0) return;
    count -= (size_t)got;
  }
}

/* The copy pipe, both ends still the preload's; a new one when an end is stale (a
   stale end is the program's now: left alone). 0 when no pipe can be made. */
static int copy_pipe_ready_locked(void) {
  int ends[2];
  if (copy_pipe[0] >= 0 && private_verified(copy_pipe[0]) && private_verified(copy_pipe[1]))
    return 1;
  if (copy_pipe[0] >= 0) {
    private_close(copy_pipe[0]);
    private_close(copy_pipe[1]);
  }
  copy_pipe[0] = copy_pipe[1] = -1;
  pthread_mutex_lock(&private_lock);
  if (syscall(SYS_pipe2, ends, O_CLOEXEC) == 0) {
    copy_pipe[0] = private_adopt_locked(ends[0]);
    copy_pipe[1] = private_adopt_locked(ends[1]);
  }
  pthread_mutex_unlock(&private_lock);
  if (copy_pipe[0] >= 0 && copy_pipe[1] >= 0) return 1;
  if (copy_pipe[0] >= 0) private_close(copy_pipe[0]);
  if (copy_pipe[1] >= 0) private_close(copy_pipe[1]);
  copy_pipe[0] = copy_pipe[1] = -1;
  return 0;
}

/* Copy size bytes from src to dst through a pipe: the kernel checks both pointers and
   answers EFAULT where the driver's copy_from_user/copy_to_user would have failed.
   0 on success, -1 when either side is not accessible. */
static int safe_copy(void *dst, const void *src, size_t size) {
  long moved;
  int rc = -1;
  if (size == 0) return 0;
  pthread_mutex_lock(&pipe_lock);
  if (!copy_pipe_ready_locked()) {
    pthread_mutex_unlock(&pipe_lock);
    return -1;
  }
  moved = syscall(SYS_write, copy_pipe[1], src, size);
  if (moved == (long)size) {
    long got = syscall(SYS_read, copy_pipe[0], dst, size);
    if (got == (long)size) rc = 0;
    else drain(size - (got > 0 ? (size_t)got : 0));
  } else if (moved > 0) {
    drain((size_t)moved);
  }
  pthread_mutex_unlock(&pipe_lock);
  return rc;
}

/* ---- the driver's answers ----------------------------------------------------------------- */

/* The board as the driver checked it: there and initialised by this process. */
static int board_ready_for_calls(unsigned board) {
  int ready;
  if (board >= MAX_DEV_BOARDS) return 0;
  pthread_mutex_lock(&board_lock);
  ready = board_opens[board] > 0 && board_mapped[board];
  pthread_mutex_unlock(&board_lock);
  return ready;
}

/* [ours] What the kernel driver never had to do, done while no device call runs in
   this process (board_lock held, calls_in_flight 0), so that no thread is inside libcif
   on a board that changes under it:
   - a board EXITDRV closed (its INITDRV count 0) is unmapped now: EXITDRV only counts,
     the calls that were in flight finished on the mapped board, as they did in the
     kernel driver, and the last of them to leave unmaps it;
   - when one of the preload's descriptors went stale (docs/legacy.md, close-all
     loops), every open board is opened anew: DevExitBoard forgets the stale
     descriptors without closing the program's files, DevInitBoard opens new ones. A
     board that does not open again answers -1 until INITDRV opens it. */
static void board_maintenance_locked(void) {
  int stale = private_any_stale();
  unsigned n;
  for (n = 0; n < MAX_DEV_BOARDS; n++) {
    if (!board_mapped[n] || (board_opens[n] > 0 && !stale)) continue;
    DevExitBoard((unsigned short)n);
    board_mapped[n] = 0;
    if (board_opens[n] > 0) board_mapped[n] = DevInitBoard((unsigned short)n) == DRV_NO_ERROR;
  }
  if (stale) private_purge_stale(); /* the image directory's, which libcif keeps open */
}

static void calls_enter(void) {
  pthread_mutex_lock(&board_lock);
  if (calls_in_flight == 0) board_maintenance_locked();
  calls_in_flight++;
  pthread_mutex_unlock(&board_lock);
}

static void calls_leave(void) {
  pthread_mutex_lock(&board_lock);
  if (--calls_in_flight == 0) board_maintenance_locked();
  pthread_mutex_unlock(&board_lock);
}

/* The image's bytes: through libcif for a board this process initialised, otherwise
   from the image file, as the driver reached every board it had detected (GETINFO,
   GETMBX, RWRAW, RWDPMDATA needed no INITDRV). DRV_BOARD_NOT_INIT when neither works. */
static short dpm_access(unsigned board, int write, unsigned offset, unsigned length,
                        void *data) {
  char path[PATH_MAX];
  long done;
  int fd;
  if (length == 0) return DRV_NO_ERROR;
  if (board_ready_for_calls(board))
    return DevReadWriteDPMData((unsigned short)board, write ? PARAMETER_WRITE : PARAMETER_READ,
                               (unsigned short)offset, (unsigned short)length, data);
  snprintf(path, sizeof path, "%s/board%u.dpm", image_directory(), board);
  fd = __wrap_open(path, (write ? O_RDWR : O_RDONLY) | O_CLOEXEC);
  if (fd < 0) return DRV_BOARD_NOT_INIT;
  /* checked by __wrap_pwrite and __wrap_pread */
  done = write ? (long)pwrite(fd, data, length, offset) : (long)pread(fd, data, length, offset);
  private_close(fd);
  return done == (long)length ? DRV_NO_ERROR : DRV_BOARD_NOT_INIT;
}

static unsigned char image_byte(unsigned board, unsigned offset) {
  unsigned char value = 0;
  dpm_access(board, 0, offset, 1, &value);
  return value;
}

/* DRIVERINFO, IOINFO or VERSIONINFO in libcif's layout: libcif's own for a board this
   process initialised, else what the image says (no counters). */
static short info_area(unsigned board, unsigned short area, void *out, unsigned short size) {
  if (board_ready_for_calls(board)) return DevGetInfo((unsigned short)board, area, size, out);
  memset(out, 0, size);
  if (area == GET_VERSION_INFO) return dpm_access(board, 0, OFS_VERSION_INFO, size, out);
  if (area == GET_IO_INFO) {
    IOINFO *io = (IOINFO *)out;
    io->bComBit = (image_byte(board, OFS_HOST_FLAGS) & FL_COM) ? 1 : 0;
    io->bIOExchangeMode = (unsigned char)(image_byte(board, OFS_DRIVER_TYPE) >> 4);
  } else {
    DRIVERINFO *info = (DRIVERINFO *)out;
    info->bHostFlags = image_byte(board, OFS_HOST_FLAGS);
    info->bMyDevFlags = image_byte(board, OFS_DEV_FLAGS);
  }
  return DRV_NO_ERROR;
}

static void native_driverinfo(drv_driverinfo *out, const DRIVERINFO *in) {
  memset(out, 0, sizeof *out);
  out->open = in->ulOpenCnt;
  out->close = in->CloseCnt;
  out->read = in->ulReadCnt;
  out->write = in->ulWriteCnt;
  out->irq = in->ulIRQCnt;
  memcpy(out->flags, (const unsigned char *)in + 5 * 4, sizeof out->flags); /* after 5 counters */
  out->exio = in->ulExIOCnt;
}

static void native_versioninfo(drv_versioninfo *out, const VERSIONINFO *in) {
  out->date = in->ulDate;
  out->device = in->ulDeviceNo;
  out->serial = in->ulSerialNo;
  out->reserved = in->ulReserved;
  memcpy(out->names, (const unsigned char *)in + 4 * 4, sizeof out->names); /* the 4 names */
}

#define COPY_IN(var) \
  do { if (safe_copy(&(var), arg, sizeof(var)) != 0) return -EFAULT; } while (0)
#define COPY_OUT(var) \
  do { if (safe_copy(arg, &(var), sizeof(var)) != 0) return -EFAULT; } while (0)

static long do_opmode(void *arg) {
  io_opmode c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) c.error = DRV_BOARD_NOT_INIT;
  else if (c.mode == POLLING_MODE || c.mode == INTERRUPT_MODE)
    c.irq = 0; /* [ours] no interrupt line: the doorbell with polling serves both modes */
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_boardinfo(void *arg) {
  io_boardinfo c;
  BOARD_INFO info;
  drv_boardinfo out;
  int n;
  COPY_IN(c);
  c.error = DevGetBoardInfo(&info);
  if (c.error == DRV_NO_ERROR) {
    memset(&out, 0, sizeof out);
    memcpy(out.version, info.abDriverVersion, sizeof out.version);
    for (n = 0; n < MAX_DEV_BOARDS; n++) {
      out.entry[n].board = info.tBoard[n].usBoard;
      out.entry[n].available = info.tBoard[n].usAvailable;
    }
    out.detected = info.usBoards_detected;
    if (safe_copy(c.info, &out, sizeof out) != 0) c.error = DRV_USR_BUF_PTR_NULL; /* [ours] */
  }
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_boardinfoex(void *arg) {
  io_boardinfo c;
  BOARD_INFOEX ex;
  drv_boardinfoex out;
  int n;
  COPY_IN(c);
  c.error = DevGetBoardInfoEx(&ex);
  if (c.error == DRV_NO_ERROR) {
    memset(&out, 0, sizeof out);
    memcpy(out.version, ex.abDriverVersion, sizeof out.version);
    for (n = 0; n < MAX_DEV_BOARDS; n++) {
      out.entry[n].board = ex.tBoard[n].usBoard;
      out.entry[n].available = ex.tBoard[n].usAvailable;
      native_driverinfo(&out.entry[n].driver, &ex.tBoard[n].tDriverInfo);
      out.entry[n].firmware = ex.tBoard[n].tFirmware;
      out.entry[n].device = ex.tBoard[n].tDeviceInfo;
      out.entry[n].rcs = ex.tBoard[n].tRcsInfo;
      native_versioninfo(&out.entry[n].version, &ex.tBoard[n].tVersion);
    }
    if (safe_copy(c.info, &out, sizeof out) != 0) c.error = DRV_USR_BUF_PTR_NULL; /* [ours] */
  }
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_initdrv(void *arg) {
  io_reset c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_exists(c.board)) {
    c.error = DRV_BOARD_NOT_INIT;
  } else {
    pthread_mutex_lock(&board_lock);
    /* a board EXITDRV closed while calls were in flight is still mapped: kept */
    if (!board_mapped[c.board]) c.error = DevInitBoard(c.board);
    if (c.error == DRV_USR_DEV_NUMBER_INVALID) c.error = DRV_BOARD_NOT_INIT; /* image gone */
    if (c.error == DRV_NO_ERROR) {
      board_mapped[c.board] = 1;
      board_opens[c.board]++;
    }
    pthread_mutex_unlock(&board_lock);
    c.dpm_size = image_byte(c.board, OFS_DPM_SIZE);
  }
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_exitdrv(void *arg) {
  io_exit c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_exists(c.board)) {
    c.error = DRV_BOARD_NOT_INIT;
  } else {
    pthread_mutex_lock(&board_lock);
    /* the unmap waits for the calls in flight: board_maintenance_locked */
    if (board_opens[c.board] == 0) c.error = DRV_BOARD_NOT_INIT;
    else board_opens[c.board]--;
    c.open_count = (uint16_t)board_opens[c.board];
    pthread_mutex_unlock(&board_lock);
  }
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_reset(void *arg) {
  io_reset c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) {
    c.error = DRV_BOARD_NOT_INIT;
  } else {
    /* the driver: 4 boot start, 3 warm start, anything else a cold start */
    unsigned short mode = c.mode == BOOTSTART || c.mode == WARMSTART ? c.mode : COLDSTART;
    c.error = DevReset(c.board, mode, c.timeout);
  }
  COPY_OUT(c);
  return (long)sizeof c;
}

/* PARAMETER: tasks 1 and 2 into their parameter areas; the driver wrote tasks 3 to 7
   into the device mailbox's memory, 64 bytes each, and so does this. */
static long do_put_parameter(void *arg) {
  io_param c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) c.error = DRV_BOARD_NOT_INIT;
  else if (c.number < 1 || c.number > 7) c.error = DRV_USR_NUMBER_INVALID;
  else if (c.length > sizeof c.data) c.error = DRV_USR_SIZE_TOO_LONG; /* [ours] */
  else if (c.length == 0) c.error = DRV_NO_ERROR;
  else if (c.number <= 2) c.error = DevPutTaskParameter(c.board, c.number, c.length, c.data);
  else
    c.error = DevReadWriteDPMData(c.board, PARAMETER_WRITE,
                                  (unsigned short)(OFS_DEV_MBX + (c.number - 3u) * 64u), c.length,
                                  c.data);
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_get_parameter(void *arg) {
  io_param c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) return -EPERM; /* the driver: -1, nothing written back */
  if (c.number != 1 && c.number != 2) {
    c.error = DRV_USR_NUMBER_INVALID;
    COPY_OUT(c);
    return -EPERM;
  }
  if (c.length > sizeof c.data) c.error = DRV_USR_SIZE_TOO_LONG; /* [ours] */
  else if (c.length > 0) c.error = DevGetTaskParameter(c.board, c.number, c.length, c.data);
  COPY_OUT(c);
  return (long)(sizeof c.error + (c.error == DRV_NO_ERROR ? c.length : 0u));
}

static long do_taskstate(void *arg) {
  io_taskstate c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) c.error = DRV_BOARD_NOT_INIT;
  else if (c.length > sizeof c.data) c.error = DRV_USR_SIZE_TOO_LONG; /* [ours] */
  else if (c.length > 0) /* the driver: 1 is task 1, any other number task 2 */
    c.error = DevGetTaskState(c.board, c.number == 1 ? 1 : 2, c.length, c.data);
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_mbxinfo(void *arg) {
  io_mbxinfo c;
  unsigned short dev_state = 0, host_state = 0;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) {
    c.error = DRV_BOARD_NOT_INIT;
  } else {
    c.error = DevGetMBXState(c.board, &dev_state, &host_state);
    if (c.error == DRV_NO_ERROR) {
      c.dev_state = dev_state;
      c.host_state = host_state;
    }
  }
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_trigger(void *arg) {
  io_trigger c;
  unsigned short value = 0;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) {
    c.error = DRV_BOARD_NOT_INIT;
  } else {
    /* the driver: 1 starts (copies the host's watchdog), anything else stops */
    c.error = DevTriggerWatchDog(c.board, c.mode == WATCHDOG_START ? WATCHDOG_START : WATCHDOG_STOP,
                                 &value);
    if (c.error == DRV_NO_ERROR) c.value = value;
  }
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_sethost(void *arg) {
  io_trigger c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) c.error = DRV_BOARD_NOT_INIT;
  else /* the driver: 1 is HOST_READY, anything else not ready */
    c.error = DevSetHostState(c.board, c.mode == HOST_READY ? HOST_READY : HOST_NOT_READY,
                              c.timeout);
  COPY_OUT(c);
  return (long)sizeof c.error;
}

static long do_spcontrol(void *arg) {
  io_trigger c;
  unsigned short ack = 0;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) {
    c.error = DRV_BOARD_NOT_INIT;
  } else if (c.mode == SPECIAL_CONTROL_SET || c.mode == SPECIAL_CONTROL_CLEAR) {
    c.error = DevSpecialControl(c.board, c.mode, &ack);
    if (c.error == DRV_NO_ERROR) c.value = ack;
  } else if (!(image_byte(c.board, OFS_HOST_FLAGS) & FL_READY)) {
    c.error = DRV_DEV_NOT_READY;
  } else { /* the driver reports the acknowledge as it is, with -37 */
    c.error = DRV_USR_MODE_INVALID;
    c.value = (image_byte(c.board, OFS_HOST_FLAGS) & FL_SPCACK) ? 1 : 0;
  }
  COPY_OUT(c);
  return (long)sizeof c.error;
}

/* GETINFO: the driver answered 0 for a board it did not have and an unknown area. */
static long do_getinfo(void *arg) {
  static const unsigned short offsets[9] = {0, 0, OFS_VERSION_INFO, OFS_FIRMWARE_INFO,
                                            OFS_TASK_INFO, OFS_RCS_INFO, OFS_DEV_INFO, 0,
                                            OFS_SND_PD};
  static const unsigned short sizes[9] = {0,  sizeof(drv_driverinfo), sizeof(drv_versioninfo),
                                          32, 112, 8, 6, sizeof(drv_ioinfo), IO_AREA_SIZE};
  unsigned char data[IO_AREA_SIZE];
  io_getinfo c;
  long done = 0;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_exists(c.board)) {
    c.error = DRV_BOARD_NOT_INIT;
  } else if (c.area < GET_DRIVER_INFO || c.area > GET_IO_SEND_DATA) {
    c.error = DRV_PARAM_UNKNOWN;
  } else if (c.length > sizes[c.area]) {
    c.error = DRV_USR_SIZE_TOO_LONG; /* [ours] */
    done = (long)sizeof c.error;
  } else {
    if (c.area == GET_DRIVER_INFO) {
      DRIVERINFO info;
      drv_driverinfo out;
      c.error = info_area(c.board, GET_DRIVER_INFO, &info, sizeof info);
      native_driverinfo(&out, &info);
      memcpy(data, &out, sizeof out);
    } else if (c.area == GET_IO_INFO) {
      IOINFO info;
      drv_ioinfo out;
      c.error = info_area(c.board, GET_IO_INFO, &info, sizeof info);
      out.com = info.bComBit;
      out.mode = info.bIOExchangeMode;
      out.count = info.ulIOExchangeCnt;
      memcpy(data, &out, sizeof out);
    } else if (c.area == GET_VERSION_INFO) {
      VERSIONINFO info;
      drv_versioninfo out;
      c.error = info_area(c.board, GET_VERSION_INFO, &info, sizeof info);
      native_versioninfo(&out, &info);
      memcpy(data, &out, sizeof out);
    } else { /* the other areas are the image's bytes */
      c.error = dpm_access(c.board, 0, offsets[c.area], c.length, data);
    }
    if (c.error == DRV_NO_ERROR && safe_copy(c.data, data, c.length) != 0)
      c.error = DRV_USR_BUF_PTR_NULL; /* [ours] */
    done = (long)(sizeof c.error + c.length);
  }
  COPY_OUT(c);
  return done;
}

static long do_readsend(void *arg) {
  unsigned char data[IO_AREA_SIZE];
  io_readsend c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_ready_for_calls(c.board)) {
    c.error = DRV_BOARD_NOT_INIT;
  } else {
    c.error = DevReadSendData(c.board, c.offset, c.length, data);
    if (c.error == DRV_NO_ERROR && safe_copy(c.data, data, c.length) != 0)
      c.error = DRV_USR_BUF_PTR_NULL; /* [ours] */
  }
  COPY_OUT(c);
  return (long)(sizeof c.error + (c.error == DRV_NO_ERROR ? c.length : 0u));
}

/* EXTDATA: the driver compared OS names and never wrote the structure back; the
   CANopen master card has no such entries. */
static long do_extdata(void *arg) {
  io_extdata c;
  COPY_IN(c);
  return (long)sizeof c;
}

static long do_getmbx(void *arg) {
  io_getmbx c;
  COPY_IN(c);
  c.error = DRV_NO_ERROR;
  if (!board_exists(c.board))
    return (long)(sizeof c.error + c.dev_length + c.host_length); /* nothing written back */
  if (c.dev_length > MSG_BUFFER_SIZE || c.host_length > MSG_BUFFER_SIZE) {
    c.error = DRV_USR_SIZE_TOO_LONG; /* [ours] */
  } else {
    c.error = dpm_access(c.board, 0, OFS_DEV_MBX, c.dev_length, c.dev);
    if (c.error == DRV_NO_ERROR) c.error = dpm_access(c.board, 0, OFS_PC_MBX, c.host_length, c.host);
  }
  COPY_OUT(c);
  return (long)(sizeof c.error + c.dev_length + c.host_length);
}

/* RWRAW and RWDPMDATA: the driver copied straight between the user's buffer and the
   DPM and never wrote the structure back. [ours] a refusal is written back. */
static long do_rawdata(void *arg, int whole_image) {
  unsigned char data[DPM_SIZE];
  io_rawdata c;
  short rc = DRV_NO_ERROR;
  COPY_IN(c);
  if (!board_exists(c.board)) {
    rc = DRV_BOARD_NOT_INIT;
  } else if (c.mode != PARAMETER_READ && c.mode != PARAMETER_WRITE) {
    rc = DRV_USR_MODE_INVALID;
  } else if ((unsigned)c.offset + c.length > (whole_image ? DPM_SIZE : RAW_AREA_LIMIT)) {
    rc = DRV_USR_SIZE_TOO_LONG;
  } else if (c.mode == PARAMETER_WRITE && safe_copy(data, c.data, c.length) != 0) {
    rc = DRV_USR_BUF_PTR_NULL;
  } else {
    rc = dpm_access(c.board, c.mode == PARAMETER_WRITE, (whole_image ? 0u : LAST_KB) + c.offset,
                    c.length, data);
    if (rc == DRV_NO_ERROR && c.mode == PARAMETER_READ && safe_copy(c.data, data, c.length) != 0)
      rc = DRV_USR_BUF_PTR_NULL;
  }
  if (rc != DRV_NO_ERROR) {
    c.error = rc;
    COPY_OUT(c);
  }
  return (long)(sizeof c.error + c.length);
}

enum exchange_kind { EXIO, EXIOEX, EXIOERR };

/* EXIO, EXIOEX, EXIOERR: a board the driver did not have answers -1 (the API object
   then returns -33); otherwise 2 + the receive length after an exchange. */
static long do_exchange(void *arg, enum exchange_kind kind) {
  unsigned char send[IO_AREA_SIZE], receive[IO_AREA_SIZE];
  union { io_exio plain; io_exioex ex; io_exioerr err; } c;
  size_t size = kind == EXIO ? sizeof c.plain : kind == EXIOEX ? sizeof c.ex : sizeof c.err;
  io_exio *io = &c.plain;
  COMSTATE state;
  long done;
  if (safe_copy(&c, arg, size) != 0) return -EFAULT;
  io->error = DRV_NO_ERROR;
  if (!board_ready_for_calls(io->board)) {
    io->error = DRV_BOARD_NOT_INIT;
    if (safe_copy(arg, &c, size) != 0) return -EFAULT;
    return -EPERM;
  }
  memset(&state, 0, sizeof state);
  if (io->send_length && (unsigned)io->send_offset + io->send_length > IO_AREA_SIZE)
    io->error = DRV_USR_SENDSIZE_TOO_LONG; /* [ours] from here to the exchange */
  else if (io->receive_length && (unsigned)io->receive_offset + io->receive_length > IO_AREA_SIZE)
    io->error = DRV_USR_RECVSIZE_TOO_LONG;
  else if (safe_copy(send, io->send, io->send_length) != 0)
    io->error = DRV_USR_SENDBUF_PTR_NULL;
  else if (safe_copy(receive, io->receive, io->receive_length) != 0)
    io->error = DRV_USR_RECVBUF_PTR_NULL;
  else if (kind == EXIOERR && safe_copy(&state, c.err.state, sizeof state) != 0)
    io->error = DRV_USR_BUF_PTR_NULL;
  else if (kind == EXIO)
    io->error = DevExchangeIO(io->board, io->send_offset, io->send_length, send,
                              io->receive_offset, io->receive_length, receive, io->timeout);
  else if (kind == EXIOEX && (c.ex.mode < 1 || c.ex.mode > 5)) {
    unsigned char flags = image_byte(io->board, OFS_HOST_FLAGS); /* the driver's order */
    io->error = !(flags & FL_READY) ? DRV_DEV_NOT_READY
                : !(flags & FL_COM) ? DRV_DEV_NO_COM_FLAG : DRV_DEV_COM_MODE_UNKNOWN;
  } else if (kind == EXIOEX)
    io->error = DevExchangeIOEx(io->board, (unsigned short)(c.ex.mode - 1u), io->send_offset,
                                io->send_length, send, io->receive_offset, io->receive_length,
                                receive, io->timeout);
  else
    io->error = DevExchangeIOErr(io->board, io->send_offset, io->send_length, send,
                                 io->receive_offset, io->receive_length, receive, &state,
                                 io->timeout);
  done = (long)sizeof io->error;
  if (io->error == DRV_NO_ERROR || io->error == DRV_DEV_NO_COM_FLAG) {
    if (safe_copy(io->receive, receive, io->receive_length) != 0)
      io->error = DRV_USR_RECVBUF_PTR_NULL;
    else if (io->error == DRV_NO_ERROR)
      done += io->receive_length;
  }
  if (kind == EXIOERR && io->error != DRV_USR_BUF_PTR_NULL &&
      safe_copy(c.err.state, &state, sizeof state) != 0)
    io->error = DRV_USR_BUF_PTR_NULL;
  if (safe_copy(arg, &c, size) != 0) return -EFAULT;
  return done;
}

static long do_putmsg(void *arg) {
  io_putmsg c;
  COPY_IN(c);
  c.error = board_ready_for_calls(c.board) ? DevPutMessage(c.board, &c.msg, c.timeout)
                                           : DRV_BOARD_NOT_INIT;
  COPY_OUT(c);
  return (long)sizeof c;
}

static long do_getmsg(void *arg) {
  io_getmsg c;
  COPY_IN(c);
  /* the driver ignored the size: the message is ln + 8 bytes of a 288-byte buffer */
  c.error = board_ready_for_calls(c.board)
                ? DevGetMessage(c.board, sizeof c.msg, &c.msg, c.timeout)
                : DRV_BOARD_NOT_INIT;
  COPY_OUT(c);
  return (long)sizeof c;
}

/* One ioctl on the device: the driver's return value, negative for -errno. */
static long device_call(unsigned long request, void *arg) {
  unsigned cmd = (unsigned)request, nr = IOC_NR(cmd);
  if (IOC_TYPE(cmd) != IOC_MAGIC || nr > NUMBER_OF_IOCTLS) return -ENOTTY;
  if (nr == 0 || (cmd != expected_cmd(nr, 1) && cmd != expected_cmd(nr, 0)))
    return 0; /* the driver's default case */
  switch (nr) {
    case NR_BOARDINFO: return do_boardinfo(arg);
    case NR_INITDRV: return do_initdrv(arg);
    case NR_PARAMETER: return do_put_parameter(arg);
    case NR_RESETDEV: return do_reset(arg);
    case NR_PUTMSG: return do_putmsg(arg);
    case NR_GETMSG: return do_getmsg(arg);
    case NR_TASKSTATE: return do_taskstate(arg);
    case NR_MBXINFO: return do_mbxinfo(arg);
    case NR_TRIGGERWD: return do_trigger(arg);
    case NR_GETINFO: return do_getinfo(arg);
    case NR_EXITDRV: return do_exitdrv(arg);
    case NR_GETPARAMETER: return do_get_parameter(arg);
    case NR_EXIO: return do_exchange(arg, EXIO);
    case NR_SETHOST: return do_sethost(arg);
    case NR_READSEND: return do_readsend(arg);
    case NR_EXTDATA: return do_extdata(arg);
    case NR_GETMBX: return do_getmbx(arg);
    case NR_BOARDINFOEX: return do_boardinfoex(arg);
    case NR_EXIOEX: return do_exchange(arg, EXIOEX);
    case NR_EXIOERR: return do_exchange(arg, EXIOERR);
    case NR_RWRAW: return do_rawdata(arg, 0);
    case NR_SPCONTROL: return do_spcontrol(arg);
    case NR_RWDPMDATA: return do_rawdata(arg, 1);
    case NR_IRQ_POLL: return do_opmode(arg);
    default: return 0; /* GETDPMPTR: the driver had no case for it */
  }
}

static long device_ioctl(unsigned long request, void *arg) {
  long done;
  calls_enter();
  done = device_call(request, arg);
  calls_leave();
  return done;
}

/* ---- the interposed libc functions ------------------------------------------------------- */

#define EXPORT __attribute__((visibility("default")))

static mode_t mode_argument(int flags, va_list args) {
#ifdef O_TMPFILE
  if ((flags & O_CREAT) || (flags & O_TMPFILE) == O_TMPFILE) return (mode_t)va_arg(args, int);
#else
  if (flags & O_CREAT) return (mode_t)va_arg(args, int);
#endif
  return 0;
}

EXPORT int open(const char *path, int flags, ...) {
  va_list args;
  mode_t mode;
  va_start(args, flags);
  mode = mode_argument(flags, args);
  va_end(args);
  if (is_device_path(path)) return device_open(flags);
  return not_a_device(real_open_named("open", path, flags, mode));
}

EXPORT int open64(const char *path, int flags, ...) {
  va_list args;
  mode_t mode;
  va_start(args, flags);
  mode = mode_argument(flags, args);
  va_end(args);
  if (is_device_path(path)) return device_open(flags);
  return not_a_device(real_open_named("open64", path, flags, mode));
}

EXPORT int openat(int dirfd, const char *path, int flags, ...) {
  va_list args;
  mode_t mode;
  va_start(args, flags);
  mode = mode_argument(flags, args);
  va_end(args);
  if (is_device_path(path)) return device_open(flags);
  return not_a_device(real_openat_named("openat", dirfd, path, flags, mode));
}

EXPORT int openat64(int dirfd, const char *path, int flags, ...) {
  va_list args;
  mode_t mode;
  va_start(args, flags);
  mode = mode_argument(flags, args);
  va_end(args);
  if (is_device_path(path)) return device_open(flags);
  return not_a_device(real_openat_named("openat64", dirfd, path, flags, mode));
}

/* _FORTIFY_SOURCE's checked forms, which programs built with it call. */
EXPORT int __open_2(const char *path, int flags) { return open(path, flags); }
EXPORT int __open64_2(const char *path, int flags) { return open(path, flags); }
EXPORT int __openat_2(int dirfd, const char *path, int flags) { return openat(dirfd, path, flags); }
EXPORT int __openat64_2(int dirfd, const char *path, int flags) {
  return openat(dirfd, path, flags);
}

EXPORT int close(int fd) {
  if (is_device_fd(fd)) {
    pthread_mutex_lock(&state_lock);
    forget_fd_locked(fd);
    pthread_mutex_unlock(&state_lock);
    /* the driver's release did nothing: boards stay initialised until EXITDRV */
  } else if (private_refuses_close(fd)) {
    errno = EBADF; /* [ours] the preload's own: for the program nothing is open there */
    return -1;
  }
  return real_close(fd);
}

#ifndef CLOSE_RANGE_UNSHARE
#define CLOSE_RANGE_UNSHARE (1U << 1)
#endif
#ifndef CLOSE_RANGE_CLOEXEC
#define CLOSE_RANGE_CLOEXEC (1U << 2)
#endif

/* Close first..last with the kernel's close_range, or one by one where it has none. */
static int close_span(unsigned first, unsigned last, int flags) {
  struct rlimit limit;
  unsigned fd, end = last;
#ifdef SYS_close_range
  if (syscall(SYS_close_range, first, last, flags) == 0) return 0;
  if (errno != ENOSYS) return -1;
#endif
  if (flags & CLOSE_RANGE_CLOEXEC) {
    errno = ENOSYS;
    return -1;
  }
  if (getrlimit(RLIMIT_NOFILE, &limit) == 0 && limit.rlim_cur != RLIM_INFINITY &&
      limit.rlim_cur <= end)
    end = (unsigned)limit.rlim_cur - 1u;
  for (fd = first; fd <= end && fd >= first; fd++) syscall(SYS_close, (int)fd);
  return 0;
}

static int compare_ints(const void *a, const void *b) {
  return (*(const int *)a > *(const int *)b) - (*(const int *)a < *(const int *)b);
}

/* glibc 2.34's close_range and closefrom: every descriptor of the range but the
   preload's own is closed [ours]. CLOSE_RANGE_CLOEXEC only marks: passed on whole. */
EXPORT int close_range(unsigned first, unsigned last, int flags) {
  int keep[MAX_PRIVATE_FDS], kept = 0, i, rc = 0;
  unsigned long long from = first; /* past ~0U when the last kept one is `last` */
  if (first > last || (flags & (int)CLOSE_RANGE_CLOEXEC)) return close_span(first, last, flags);
  pthread_mutex_lock(&private_lock);
  for (i = 0; i < private_count; i++) {
    unsigned fd = (unsigned)private_fds[i].fd;
    if (fd >= first && fd <= last && private_valid_locked(&private_fds[i]))
      keep[kept++] = private_fds[i].fd;
  }
  pthread_mutex_unlock(&private_lock);
  qsort(keep, (size_t)kept, sizeof keep[0], compare_ints);
  for (i = 0; i <= kept && rc == 0; i++) {
    unsigned long long to = i < kept ? (unsigned long long)keep[i] - 1u : last;
    if (from <= to) {
      rc = close_span((unsigned)from, (unsigned)to, flags);
      flags &= ~(int)CLOSE_RANGE_UNSHARE; /* the table is this process's own from the first */
    }
    if (i < kept) from = (unsigned long long)keep[i] + 1u;
  }
  pthread_mutex_lock(&state_lock);
  for (i = device_fd_count - 1; i >= 0; i--)
    if ((unsigned)device_fds[i] >= first && (unsigned)device_fds[i] <= last)
      forget_fd_locked(device_fds[i]);
  pthread_mutex_unlock(&state_lock);
  return rc;
}

EXPORT void closefrom(int lowfd) {
  if (lowfd >= 0) close_range((unsigned)lowfd, ~0U, 0);
}

static int ioctl_common(int fd, unsigned long request, void *arg) {
  static int trace = -1;
  long done;
  if (!is_device_fd(fd)) return real_ioctl(fd, request, arg);
  done = device_ioctl(request, arg);
  if (trace < 0) trace = getenv("CIFDEV_TRACE") != NULL;
  if (trace) /* [ours] CIFDEV_TRACE=1: each ioctl, its return and the structure's sError */
    fprintf(stderr, "cifdev: ioctl(%d, 0x%08lx, %p) = %ld\n", fd, request, arg, done);
  if (done < 0) {
    errno = (int)-done;
    return -1;
  }
  return (int)done;
}

EXPORT int ioctl(int fd, unsigned long request, ...) {
  va_list args;
  void *arg;
  va_start(args, request);
  arg = va_arg(args, void *);
  va_end(args);
  return ioctl_common(fd, request, arg);
}

#if defined(__i386__)
/* i386 programs built with 64-bit time_t call this name */
EXPORT int __ioctl_time64(int fd, unsigned long request, ...) {
  va_list args;
  void *arg;
  va_start(args, request);
  arg = va_arg(args, void *);
  va_end(args);
  return ioctl_common(fd, request, arg);
}
#endif

/* A duplicate of the device's descriptor is the device as well. */
static int track_duplicate(int oldfd, int newfd) {
  if (newfd < 0) return newfd;
  pthread_mutex_lock(&state_lock);
  forget_fd_locked(newfd);
  pthread_mutex_unlock(&state_lock);
  if (is_device_fd(oldfd)) {
    pthread_mutex_lock(&state_lock);
    remember_fd_locked(newfd);
    pthread_mutex_unlock(&state_lock);
  }
  return newfd;
}

static int fcntl_common(int fd, int cmd, void *arg) {
  int done = real_fcntl(fd, cmd, arg);
  if (cmd == F_DUPFD || cmd == F_DUPFD_CLOEXEC) track_duplicate(fd, done);
  return done;
}

EXPORT int fcntl(int fd, int cmd, ...) {
  va_list args;
  void *arg;
  va_start(args, cmd);
  arg = va_arg(args, void *);
  va_end(args);
  return fcntl_common(fd, cmd, arg);
}

EXPORT int fcntl64(int fd, int cmd, ...) {
  va_list args;
  void *arg;
  va_start(args, cmd);
  arg = va_arg(args, void *);
  va_end(args);
  return fcntl_common(fd, cmd, arg);
}

#if defined(__i386__)
/* i386 programs built with 64-bit time_t call this name */
EXPORT int __fcntl_time64(int fd, int cmd, ...) {
  va_list args;
  void *arg;
  va_start(args, cmd);
  arg = va_arg(args, void *);
  va_end(args);
  return fcntl_common(fd, cmd, arg);
}
#endif

EXPORT int dup(int fd) { return track_duplicate(fd, (int)syscall(SYS_dup, fd)); }

EXPORT int dup2(int oldfd, int newfd) {
  int done;
  if (oldfd == newfd) return fcntl(oldfd, F_GETFD) < 0 ? -1 : newfd;
  done = (int)syscall(SYS_dup3, oldfd, newfd, 0);
  return track_duplicate(oldfd, done);
}

EXPORT int dup3(int oldfd, int newfd, int flags) {
  return track_duplicate(oldfd, (int)syscall(SYS_dup3, oldfd, newfd, flags));
}

/* The driver's read gave 0 bytes and its write failed with ENOMEM. */
EXPORT ssize_t read(int fd, void *buf, size_t count) {
  if (is_device_fd(fd)) return 0;
  return (ssize_t)syscall(SYS_read, fd, buf, count);
}

EXPORT ssize_t write(int fd, const void *buf, size_t count) {
  if (is_device_fd(fd)) {
    errno = ENOMEM;
    return -1;
  }
  return (ssize_t)syscall(SYS_write, fd, buf, count);
}
