/*
 * legacy_ioctl.c - a legacy host as the Hilscher API object reaches the card: through
 * /dev/cif, one ioctl per driver function with its packed DEVIO structure.
 *
 * It includes none of libcif: the structures are declared here with the driver
 * header's native `unsigned long` and pointers (so an i386 build lays them out as
 * i386 programs did, an x86-64 build as x86-64 programs), and each call reads its
 * answer the way the API object did: a zero return of ioctl is DRV_USR_COMM_ERR
 * (-33; for the exchange calls a return <= 0), otherwise sError.
 *
 *   legacy_ioctl GENERATION DBM    GENERATION 26 (driver 2.6) or 2100 (driver 2.100)
 *   legacy_ioctl nodevice          only the open, where no card is
 *   legacy_ioctl smoke             open, INITDRV and GETINFO only
 *
 * Prints one "name=value" line per step; tests/test_legacy.py compares them. Run it
 * with libcifdev.so preloaded against a card with simulated nodes.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <unistd.h>

#define COMM_ERR (-33)

#pragma pack(push, 1)
typedef struct { unsigned char rx, tx, ln, nr, a, f, b, e, data[255], dummy[25]; } msg_t;
typedef struct { unsigned short board, mode, irq; short error; } opmode_t;
typedef struct { unsigned short board, length; void *info; short error; } boardinfo_cmd;
typedef struct { unsigned short board, mode; unsigned long timeout, dpm_size; short error; } reset_cmd;
typedef struct { unsigned short board, number, length; unsigned char data[64]; short error; } param_cmd;
typedef struct { unsigned short board; msg_t msg; unsigned long timeout; short error; } putmsg_cmd;
typedef struct { unsigned short board; unsigned long timeout, size; msg_t msg; short error; } getmsg_cmd;
typedef struct { unsigned char board; unsigned short number, length; unsigned char data[64]; short error; } taskstate_cmd;
typedef struct { unsigned char board; unsigned short dev, host; short error; } mbxinfo_cmd;
typedef struct { unsigned short board, mode; unsigned long timeout; unsigned short value; short error; } trigger_cmd;
typedef struct { unsigned short board, area, length; void *data; short error; } getinfo_cmd;
typedef struct { unsigned short board, count; short error; } exit_cmd;
typedef struct {
  unsigned short board, send_offset, send_length;
  void *send;
  unsigned short receive_offset, receive_length;
  void *receive;
  unsigned long timeout;
  short error;
} exio_cmd;
typedef struct { exio_cmd io; unsigned short mode; } exioex_cmd;
typedef struct { exio_cmd io; void *state; } exioerr_cmd;
typedef struct { unsigned short board, offset, length; void *data; short error; } readsend_cmd;
typedef struct { unsigned short board, mode; void *data; short error; } extdata_cmd;
typedef struct { unsigned short board, dev_length, host_length; unsigned char host[288], dev[288]; short error; } getmbx_cmd;
typedef struct { unsigned short board, mode, offset, length; void *data; short error; } raw_cmd;
typedef struct { unsigned short mode, flag; unsigned char state[64]; } comstate_t;
typedef struct {
  char version[16];
  struct { unsigned short board, available; unsigned long address; unsigned short irq; } entry[4];
  unsigned short detected;
} boardinfo_t;
typedef struct {
  unsigned long open, close, read, write, irq;
  unsigned char flags[9];
  unsigned long exio;
} driverinfo_t;
typedef struct { unsigned char com, mode; unsigned long count; } ioinfo_t;
typedef struct {
  char version[16];
  struct {
    unsigned short board, available;
    unsigned long address;
    unsigned short irq;
    driverinfo_t driver;
    char firmware[32];
    unsigned char device[6], rcs[8];
    unsigned long date, device_no, serial, reserved;
    unsigned char names[16];
  } entry[4];
} boardinfoex_t;
#pragma pack(pop)

/* The ioctl numbers: five of them carry a size, and the generations disagree there. */
static int generation_26;
#define NR(n) _IO('c', n)
static unsigned long sized(int n) {
  switch (n) {
    case 1: return generation_26 ? _IOWR('c', 1, char[256]) : _IOWR('c', 1, int);
    case 2: return generation_26 ? _IOWR('c', 2, char[13]) : _IOWR('c', 2, int);
    case 3: return generation_26 ? _IOW('c', 3, char[71]) : _IOW('c', 3, int);
    case 4: return generation_26 ? _IOW('c', 4, char[13]) : _IOW('c', 4, int);
    default: return generation_26 ? _IOWR('c', 25, char[13]) : _IOWR('c', 25, int);
  }
}
#define BOARDINFO sized(1)
#define INITDRV sized(2)
#define PARAMETER sized(3)
#define RESETDEV sized(4)
#define PUTMSG NR(5)
#define GETMSG NR(6)
#define TASKSTATE NR(7)
#define MBXINFO NR(8)
#define TRIGGERWD NR(9)
#define GETINFO NR(10)
#define EXITDRV NR(11)
#define GETPARAMETER NR(12)
#define EXIO NR(13)
#define SETHOST NR(14)
#define READSEND NR(15)
#define EXTDATA NR(16)
#define GETMBX NR(17)
#define BOARDINFOEX NR(18)
#define EXIOEX NR(19)
#define EXIOERR NR(20)
#define RWRAW NR(21)
#define SPCONTROL NR(22)
#define GETDPMPTR NR(23)
#define RWDPMDATA NR(24)
#define IRQ_POLL sized(25)

static int fd = -1;
static int last_errno;

/* As the API object: ioctl's 0 is a failed call, anything else hands over sError. */
static short call(unsigned long request, void *cmd, const short *error) {
  int done = ioctl(fd, request, cmd);
  last_errno = done < 0 ? errno : 0;
  return done == 0 ? COMM_ERR : *error;
}
/* The exchange calls: a return <= 0 is a failed call. */
static short call_io(unsigned long request, void *cmd, const short *error) {
  int done = ioctl(fd, request, cmd);
  last_errno = done < 0 ? errno : 0;
  return done <= 0 ? COMM_ERR : *error;
}

#define SHOW(name, value) printf("%s=%d\n", name, (int)(value))

static short put_msg(unsigned short board, const msg_t *msg, unsigned long timeout) {
  putmsg_cmd c;
  memset(&c, 0, sizeof c);
  c.board = board;
  c.msg = *msg;
  c.timeout = timeout;
  return call(PUTMSG, &c, &c.error);
}

static short get_msg(unsigned short board, msg_t *msg, unsigned long timeout) {
  getmsg_cmd c;
  memset(&c, 0, sizeof c);
  c.board = board;
  c.timeout = timeout;
  c.size = sizeof c.msg;
  {
    short rc = call(GETMSG, &c, &c.error);
    *msg = c.msg;
    return rc;
  }
}

static short init_board(unsigned short board, unsigned long *dpm_size) {
  reset_cmd c;
  memset(&c, 0, sizeof c);
  c.board = board;
  {
    short rc = call(INITDRV, &c, &c.error);
    *dpm_size = c.dpm_size;
    return rc;
  }
}

static short reset(unsigned short mode, unsigned long timeout) {
  reset_cmd c;
  memset(&c, 0, sizeof c);
  c.mode = mode;
  c.timeout = timeout;
  return call(RESETDEV, &c, &c.error);
}

static short host_state(unsigned short board, unsigned short mode, unsigned long timeout) {
  trigger_cmd c;
  memset(&c, 0, sizeof c);
  c.board = board;
  c.mode = mode;
  c.timeout = timeout;
  return call(SETHOST, &c, &c.error);
}

static short trigger(unsigned long request, unsigned short mode, unsigned short *value) {
  trigger_cmd c;
  memset(&c, 0, sizeof c);
  c.mode = mode;
  {
    short rc = call(request, &c, &c.error);
    *value = c.value;
    return rc;
  }
}

static short get_info(unsigned short board, unsigned short area, unsigned short length, void *data) {
  getinfo_cmd c;
  memset(&c, 0, sizeof c);
  c.board = board;
  c.area = area;
  c.length = length;
  c.data = data;
  {
    short rc = call(GETINFO, &c, &c.error);
    if (rc == COMM_ERR) printf("getinfo_serror=%d\n", c.error);
    return rc;
  }
}

static short param(unsigned long request, unsigned short number, unsigned short length,
                   unsigned char *data) {
  param_cmd c;
  memset(&c, 0, sizeof c);
  c.number = number;
  c.length = length;
  if (request != GETPARAMETER) memcpy(c.data, data, length < 64 ? length : 64);
  {
    short rc = call(request, &c, &c.error);
    if (request == GETPARAMETER) memcpy(data, c.data, length < 64 ? length : 64);
    return rc;
  }
}

static short exchange(unsigned long request, unsigned short board, unsigned short mode,
                      unsigned short offset, unsigned short length, void *send, void *receive,
                      comstate_t *state) {
  union { exio_cmd io; exioex_cmd ex; exioerr_cmd err; } c;
  memset(&c, 0, sizeof c);
  c.io.board = board;
  c.io.send_offset = offset;
  c.io.send_length = length;
  c.io.send = send;
  c.io.receive_offset = offset;
  c.io.receive_length = length;
  c.io.receive = receive;
  c.io.timeout = 1000;
  c.ex.mode = mode;
  if (request == EXIOERR) c.err.state = state;
  return call_io(request, &c, &c.io.error);
}

static short raw(unsigned long request, unsigned short mode, unsigned short offset,
                 unsigned short length, void *data) {
  raw_cmd c;
  memset(&c, 0, sizeof c);
  c.mode = mode;
  c.offset = offset;
  c.length = length;
  c.data = data;
  return call(request, &c, &c.error);
}

/* ---- DBM download, as the API object's DevDownload: put and get through the device ---- */

static unsigned word(const unsigned char *p) { return p[0] | (unsigned)p[1] << 8; }

static short transfer(unsigned char nr, const unsigned char *data, unsigned ln, unsigned char e,
                      unsigned long timeout) {
  msg_t msg, answer;
  short rc;
  memset(&msg, 0, sizeof msg);
  msg.rx = 0;    /* RCS task */
  msg.tx = 16;   /* a user task */
  msg.ln = (unsigned char)ln;
  msg.nr = nr;
  msg.b = 6;     /* RCS_B_LOADFKT */
  msg.e = e;
  memcpy(msg.data, data, ln);
  rc = put_msg(0, &msg, 500);
  while (rc == 0) {
    rc = get_msg(0, &answer, timeout);
    if (rc == 0 && answer.nr == nr && answer.a == msg.b && answer.rx == msg.tx) break;
  }
  return rc != 0 ? rc : answer.f ? (short)(1000 + answer.f) : 0;
}

static short download(const char *path, unsigned long *bytes) {
  static unsigned char file[70000];
  unsigned char first[1 + 16 + 34];
  const unsigned char *area = file + 44;
  size_t size, offset, directory, record;
  unsigned char nr = 0;
  short rc;
  FILE *f = fopen(path, "rb");
  if (f == NULL) return -100;
  size = fread(file, 1, sizeof file, f);
  fclose(f);
  if (size <= 44 + 34) return -104;
  size -= 44;
  /* GLOBAL's record: root slot 8 names the directory, its first entry the record */
  directory = word(area + 16);
  record = word(area + 2 * directory + 14);
  first[0] = 3; /* MODE_DOWNLOAD_DBM */
  memcpy(first + 1, area, 16);
  memcpy(first + 17, area + 2 * record + 12, 34);
  rc = transfer(++nr, first, sizeof first, 0x04, 10000);
  for (offset = 0; rc == 0 && offset < size; offset += 240) {
    int last = offset + 240 >= size;
    unsigned ln = (unsigned)(last ? size - offset : 240);
    rc = transfer(++nr, area + offset, ln, last ? 0x0C : 0x08, last ? 15000 : 1000);
    if (rc == 0) *bytes = offset + ln;
  }
  return rc;
}

int main(int argc, char **argv) {
  unsigned char buffer[8192], out[16], in[16], pattern[4] = {1, 2, 3, 4};
  unsigned long dpm_size = 0, bytes = 0;
  unsigned short value = 0;
  comstate_t state;
  msg_t msg;
  int mode, i;
  if (argc == 2 && strcmp(argv[1], "nodevice") == 0) { /* no card: the open fails */
    fd = open("/dev/cif", O_RDONLY);
    printf("open=%d errno=%s\n", fd, fd < 0 && errno == ENODEV ? "ENODEV" : "other");
    return 0;
  }
  if (argc == 2 && strcmp(argv[1], "smoke") == 0) { /* open, INITDRV, GETINFO only */
    fd = open("/dev/cif", O_RDONLY);
    SHOW("open", fd >= 0);
    SHOW("initdrv", init_board(0, &dpm_size));
    SHOW("getinfo_firmware", get_info(0, 3, 32, buffer));
    printf("firmware=%.14s\n", buffer);
    SHOW("initdrv_absent", init_board(1, &dpm_size));
    return 0;
  }
  if (argc != 3) {
    fprintf(stderr, "usage: legacy_ioctl 26|2100 DBM | legacy_ioctl nodevice|smoke\n");
    return 2;
  }
  generation_26 = strcmp(argv[1], "26") == 0;
  setvbuf(stdout, NULL, _IONBF, 0);
  memset(&msg, 0, sizeof msg);

  /* ---- the device itself ---- */
  SHOW("close_unopened", close(1000) == -1 && errno == EBADF);
  fd = open("/dev/cif", O_RDONLY);
  SHOW("open", fd >= 0);
  SHOW("fcntl", fcntl(fd, F_SETFD, FD_CLOEXEC) == 0 && fcntl(fd, F_GETFD) == FD_CLOEXEC);
  SHOW("read", read(fd, buffer, 4));
  SHOW("write_enomem", write(fd, buffer, 4) == -1 && errno == ENOMEM);
  { /* a duplicate is the device too (a write to /dev/null would succeed) */
    int copy = dup(fd), copy2 = fcntl(fd, F_DUPFD_CLOEXEC, 50);
    SHOW("dup_is_device", write(copy, buffer, 4) == -1 && write(copy2, buffer, 4) == -1);
    close(copy);
    close(copy2);
    SHOW("closed_dup_is_not", write(copy, buffer, 4) == -1 && errno == EBADF);
  }

  /* ---- board information, initialisation ---- */
  {
    boardinfo_t info;
    boardinfo_cmd c = {0, sizeof info, &info, 0};
    SHOW("boardinfo", call(BOARDINFO, &c, &c.error));
    SHOW("boards_detected", info.detected);
    SHOW("board0_available", info.entry[0].available);
    SHOW("board1_available", info.entry[1].available);
  }
  /* the driver served these for any board it had, before INITDRV */
  SHOW("getinfo_before_initdrv", get_info(0, 3, 32, buffer));
  printf("firmware_before_initdrv=%.14s\n", buffer);
  SHOW("rwdpm_before_initdrv", raw(RWDPMDATA, 1, 0x1FFB, 3, buffer));
  printf("identifier_before_initdrv=%.3s\n", buffer);
  SHOW("putmsg_before_initdrv", put_msg(0, &msg, 0));
  SHOW("initdrv", init_board(0, &dpm_size));
  SHOW("dpm_size", dpm_size);
  SHOW("initdrv_absent", init_board(1, &dpm_size));
  SHOW("initdrv_board9", init_board(9, &dpm_size));
  {
    boardinfoex_t ex;
    boardinfo_cmd c = {0, sizeof ex, &ex, 0};
    SHOW("boardinfoex", call(BOARDINFOEX, &c, &c.error));
    printf("boardinfoex_firmware=%.14s\n", ex.entry[0].firmware);
    SHOW("boardinfoex_opens", ex.entry[0].driver.open);
  }

  /* ---- information areas ---- */
  SHOW("getinfo_firmware", get_info(0, 3, 32, buffer));
  printf("firmware=%.14s\n", buffer);
  SHOW("getinfo_driver", get_info(0, 1, sizeof(driverinfo_t), buffer));
  SHOW("getinfo_version", get_info(0, 2, 4 * sizeof(unsigned long) + 16, buffer));
  SHOW("getinfo_task", get_info(0, 4, 112, buffer));
  SHOW("getinfo_rcs", get_info(0, 5, 8, buffer));
  SHOW("getinfo_dev", get_info(0, 6, 6, buffer));
  printf("dev_identifier=%.3s\n", buffer + 3);
  SHOW("getinfo_io", get_info(0, 7, sizeof(ioinfo_t), buffer));
  SHOW("getinfo_send", get_info(0, 8, 16, buffer));
  SHOW("getinfo_area9", get_info(0, 9, 4, buffer));
  SHOW("getinfo_board3", get_info(3, 3, 32, buffer));
  SHOW("getinfo_too_long", get_info(0, 3, 200, buffer));
  SHOW("getinfo_bad_pointer", get_info(0, 3, 32, (void *)8));

  /* ---- mailboxes: a round trip, and the codes of an empty one ---- */
  {
    mbxinfo_cmd c = {0, 7, 7, 0};
    SHOW("mbxinfo", call(MBXINFO, &c, &c.error));
    SHOW("mbx_dev", c.dev);
    SHOW("mbx_host", c.host);
  }
  SHOW("sethost_ready", host_state(0, 1, 0));
  memset(&msg, 0, sizeof msg);
  msg.rx = 2;   /* PLC task: COM_Shared_Memory reads the receive area */
  msg.tx = 16;
  msg.ln = 8;
  msg.nr = 1;
  msg.b = 17;
  msg.data[1] = 1;
  msg.data[2] = 200;
  msg.data[5] = 2;
  msg.data[6] = 5;
  msg.data[7] = 1;
  SHOW("putmsg", put_msg(0, &msg, 1000));
  memset(&msg, 0, sizeof msg);
  SHOW("getmsg", get_msg(0, &msg, 2000));
  printf("answer=%d,%d,%d,%d,%d\n", msg.rx, msg.tx, msg.nr, msg.a, msg.f);
  SHOW("getmsg_empty", get_msg(0, &msg, 0));
  SHOW("getmsg_timeout", get_msg(0, &msg, 50));
  SHOW("putmsg_board7", put_msg(7, &msg, 0));
  {
    getmbx_cmd c;
    memset(&c, 0, sizeof c);
    c.dev_length = 288;
    c.host_length = 288;
    SHOW("getmbx", call(GETMBX, &c, &c.error));
    SHOW("getmbx_host_nr", c.host[3]);
    c.dev_length = 300;
    SHOW("getmbx_too_long", call(GETMBX, &c, &c.error));
  }

  /* ---- task areas ---- */
  {
    taskstate_cmd c;
    memset(&c, 0, sizeof c);
    c.number = 1;
    c.length = 64;
    SHOW("taskstate", call(TASKSTATE, &c, &c.error));
    c.length = 65;
    SHOW("taskstate_too_long", call(TASKSTATE, &c, &c.error));
  }
  SHOW("getparameter", param(GETPARAMETER, 2, 64, buffer));
  SHOW("getparameter_task5", param(GETPARAMETER, 5, 8, buffer));
  SHOW("getparameter_task5_errno", last_errno);
  SHOW("putparameter_task9", param(PARAMETER, 9, 8, buffer));
  SHOW("putparameter_too_long", param(PARAMETER, 2, 100, buffer));

  /* ---- a DBM download, a cold start, and the card runs from it ---- */
  SHOW("download", download(argv[2], &bytes));
  printf("download_bytes=%lu\n", bytes);
  SHOW("reset_cold", reset(2, 15000));
  SHOW("sethost_com", host_state(0, 1, 5000));

  /* ---- process data in each handshake mode the card offers (bMode 1, 2, 3) ---- */
  for (mode = 1; mode <= 3; mode++) {
    ioinfo_t io;
    char name[40];
    param(GETPARAMETER, 2, 64, buffer);
    buffer[0] = (unsigned char)mode;
    snprintf(name, sizeof name, "mode%d_putparameter", mode);
    SHOW(name, param(PARAMETER, 2, 64, buffer));
    snprintf(name, sizeof name, "mode%d_reset_warm", mode);
    SHOW(name, reset(3, 15000));
    snprintf(name, sizeof name, "mode%d_sethost", mode);
    SHOW(name, host_state(0, 1, 5000));
    get_info(0, 7, sizeof io, &io);
    snprintf(name, sizeof name, "mode%d_driver_mode", mode);
    SHOW(name, io.mode);
    for (i = 0; i < 4; i++) out[i] = (unsigned char)(mode * 16 + i);
    snprintf(name, sizeof name, "mode%d_exio", mode);
    SHOW(name, exchange(EXIO, 0, 0, 0, 4, out, in, NULL));
    snprintf(name, sizeof name, "mode%d_exioex", mode);
    SHOW(name, exchange(EXIOEX, 0, io.mode, 0, 4, out, in, NULL));
    snprintf(name, sizeof name, "mode%d_exioerr", mode);
    SHOW(name, exchange(EXIOERR, 0, 0, 0, 4, out, in, &state));
    {
      readsend_cmd c = {0, 0, 4, buffer, 0};
      snprintf(name, sizeof name, "mode%d_readsend", mode);
      SHOW(name, call(READSEND, &c, &c.error));
      snprintf(name, sizeof name, "mode%d_sent", mode);
      SHOW(name, memcmp(buffer, out, 4) == 0);
    }
  }
  SHOW("exio_send_too_long", exchange(EXIO, 0, 0, 3580, 8, out, in, NULL));
  SHOW("exio_bad_send", exchange(EXIO, 0, 0, 0, 4, (void *)8, in, NULL));
  SHOW("exio_bad_receive", exchange(EXIO, 0, 0, 0, 4, out, (void *)8, NULL));
  SHOW("exio_board3", exchange(EXIO, 3, 0, 0, 4, out, in, NULL));
  SHOW("exio_board3_errno", last_errno);
  SHOW("exioex_mode0", exchange(EXIOEX, 0, 0, 0, 4, out, in, NULL));
  SHOW("exioex_mode6", exchange(EXIOEX, 0, 6, 0, 4, out, in, NULL));
  SHOW("exioerr_bad_state", exchange(EXIOERR, 0, 0, 0, 4, out, in, (void *)8));

  /* ---- watchdog, special control ---- */
  SHOW("watchdog_start", trigger(TRIGGERWD, 1, &value));
  {
    unsigned char dev_watchdog = 0;
    raw(RWDPMDATA, 1, 0x1FF4, 1, &dev_watchdog);
    SHOW("watchdog_copied", value == dev_watchdog); /* the card moves its own on */
  }
  SHOW("watchdog_stop", trigger(TRIGGERWD, 0, &value));
  SHOW("watchdog_stopped", value);
  SHOW("spcontrol_set", trigger(SPCONTROL, 1, &value));
  SHOW("spcontrol_clear", trigger(SPCONTROL, 0, &value));
  SHOW("spcontrol_mode5", trigger(SPCONTROL, 5, &value));

  /* ---- DPM access ---- */
  SHOW("rwraw_read", raw(RWRAW, 1, 0x3FB, 3, buffer));
  printf("rwraw_identifier=%.3s\n", buffer);
  SHOW("rwraw_too_long", raw(RWRAW, 1, 1020, 8, buffer));
  SHOW("rwraw_mode7", raw(RWRAW, 7, 0, 4, buffer));
  SHOW("rwdpm_write", raw(RWDPMDATA, 2, 0x0100, 4, pattern));
  memset(buffer, 0, 4);
  SHOW("rwdpm_read", raw(RWDPMDATA, 1, 0x0100, 4, buffer));
  SHOW("rwdpm_roundtrip", memcmp(buffer, pattern, 4) == 0);
  SHOW("rwdpm_too_long", raw(RWDPMDATA, 1, 8190, 4, buffer));
  SHOW("rwdpm_bad_pointer", raw(RWDPMDATA, 1, 0, 4, (void *)8));

  /* ---- the rest ---- */
  {
    extdata_cmd c = {0, 1, buffer, 0};
    SHOW("extdata", call(EXTDATA, &c, &c.error));
  }
  {
    opmode_t c = {0, 0, 77, 0};
    SHOW("irq_poll_polling", call(IRQ_POLL, &c, &c.error));
    SHOW("irq_poll_irq", c.irq);
    c.mode = 1;
    SHOW("irq_poll_interrupt", call(IRQ_POLL, &c, &c.error));
  }
  {
    char c[32];
    SHOW("getdpmptr", call(GETDPMPTR, c, (short *)c));
  }
  {
    boardinfo_cmd c = {0, 58, (void *)8, 0};
    SHOW("boardinfo_bad_pointer", call(BOARDINFO, &c, &c.error));
    SHOW("boardinfoex_bad_pointer", call(BOARDINFOEX, &c, &c.error));
  }
  {
    readsend_cmd c = {0, 0, 4, (void *)8, 0};
    SHOW("readsend_bad_pointer", call(READSEND, &c, &c.error));
  }
  SHOW("rwraw_write_bad_pointer", raw(RWRAW, 2, 0, 4, (void *)8));
  { /* every number of both generations with no structure, or one at a wild address:
       EFAULT (or the driver's 0 for GETDPMPTR), never a crash */
    int n, ok = 1, generation;
    for (generation = 0; generation < 2; generation++) {
      generation_26 = generation;
      for (n = 1; n <= 25; n++) {
        unsigned long cmd = (n <= 4 || n == 25) ? sized(n) : NR(n);
        int want = n == 23 ? 0 : -1;
        if (ioctl(fd, cmd, NULL) != want || (want == -1 && errno != EFAULT)) ok = 0;
        if (ioctl(fd, cmd, (void *)8) != want || (want == -1 && errno != EFAULT)) ok = 0;
      }
    }
    generation_26 = strcmp(argv[1], "26") == 0;
    SHOW("null_structures", ok);
  }
  SHOW("unknown_nr26", ioctl(fd, NR(26), buffer) == -1 && errno == ENOTTY);
  SHOW("unknown_type", ioctl(fd, _IO('x', 1), buffer) == -1 && errno == ENOTTY);
  SHOW("bad_structure", ioctl(fd, INITDRV, (void *)16) == -1 && errno == EFAULT);
  SHOW("reset_warm", reset(3, 15000));

  /* ---- exit and close ---- */
  {
    exit_cmd c = {0, 9, 0};
    SHOW("exitdrv", call(EXITDRV, &c, &c.error));
    SHOW("exitdrv_count", c.count);
    SHOW("exitdrv_again", call(EXITDRV, &c, &c.error));
  }
  SHOW("putmsg_after_exit", put_msg(0, &msg, 0));
  SHOW("close", close(fd));
  SHOW("close_again", close(fd) == -1 && errno == EBADF);
  fd = open("/dev/cif", O_RDWR | O_NONBLOCK);
  SHOW("reopen_rdwr", fd >= 0);
  SHOW("close_reopened", close(fd));
  return 0;
}
