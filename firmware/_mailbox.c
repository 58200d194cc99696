/*
 * firmware._mailbox - the device loop's mailbox turn for a plain COM_Shared_Memory read,
 * without the interpreter (issue 22) [ours].
 *
 * A host that polls the process image through the mailbox makes the card wake, take the
 * message, answer it and ring, once per round trip: in Python that turn cost about 70 calls
 * and most of the card's CPU per round trip. ``serve`` waits on the device's bell with the
 * interpreter lock released and answers, in a loop, every COM_Shared_Memory read (and every
 * malformed COM_Shared_Memory request) that a known host rings for, as long as nothing else
 * asks for the Python turn: it returns to the caller on a timeout, on a ring from anyone but
 * the expected host (the card's own threads ring for stops, calls, indications and state
 * changes), on any other message, on a change of the flags other than the mailbox toggles,
 * of the watchdog trigger, the output area or the connection bits, and whenever the turn
 * lock or the process image's lock is taken. The caller (firmware/device.py) checks the rest
 * (faults, queues, poll state) before it calls. A recording card's turns are served here too:
 * each appends the events its recorder's hooks would have (below). A host SDO request
 * (COM_SDO_Up_Download, msg.e 0 or 4) from the expected host is taken here too and handed to
 * the CAN task's one Python callable (sdo_turn): an expedited transfer to a simulated node of
 * this process then costs no Python turn of the device loop (not while recording: the
 * recorder's hooks see those in the Python turn). Every layout offset, flag bit,
 * command number and msg.f comes from dpm/ through ``configure``; nothing here is a number
 * of the protocol.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <errno.h>
#include <poll.h>
#include <stddef.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <time.h>

#define MAX_TYPES 8

/* What configure() took from dpm/ and firmware/plc.py. */
static struct {
  int ready;
  Py_ssize_t dev_mbx, pc_mbx, host_flags, dev_flags, dev_watchdog, snd_pd, conn_status;
  Py_ssize_t conn_size, io_size, msg_max, header;
  unsigned char hostcom, devack, hostack, devcom, host_mbx, dev_mbx_bit, nak, ring;
  int plc_task, command, read, write, area_by_function, area_receive, area_send;
  int bit_type, uint16_type;
  int f_unknown_function, f_unknown_data_type, f_illegal_area, f_illegal_count, f_overflow;
  int can_task, com_sdo, sdo_long_first;
  Py_ssize_t task2_state, task2_size;
  int ntypes, type_code[MAX_TYPES], max_address[MAX_TYPES], max_count[MAX_TYPES];
} cfg;

PyDoc_STRVAR(configure_doc,
             "configure(layout: dict[str, int], types: tuple[tuple[int, int, int], ...])\n\n"
             "The offsets, bits, numbers and msg.f of dpm/ (by name), and per data type its\n"
             "code, highest address and highest count (firmware/plc.py).");

static int take(PyObject *layout, const char *name, long *value) {
  PyObject *item = PyDict_GetItemString(layout, name); /* borrowed */
  if (item == NULL) {
    PyErr_Format(PyExc_KeyError, "configure: %s missing", name);
    return -1;
  }
  *value = PyLong_AsLong(item);
  return (*value == -1 && PyErr_Occurred()) ? -1 : 0;
}

/* One number of a table (layout or spool) by name into its field; NULL from the caller. */
#define TAKE_INTO(table, target, name)              \
  do {                                              \
    long v_;                                        \
    if (take(table, name, &v_) < 0) return NULL;    \
    target = v_;                                    \
  } while (0)
#define TAKE(field, name) TAKE_INTO(layout, cfg.field, name)

static PyObject *configure(PyObject *self, PyObject *args) {
  PyObject *layout, *types;
  Py_ssize_t i, n;
  (void)self;
  if (!PyArg_ParseTuple(args, "O!O!", &PyDict_Type, &layout, &PyTuple_Type, &types)) return NULL;
  TAKE(dev_mbx, "DEV_MBX");
  TAKE(pc_mbx, "PC_MBX");
  TAKE(host_flags, "HOST_FLAGS");
  TAKE(dev_flags, "DEV_FLAGS");
  TAKE(dev_watchdog, "DEV_WATCHDOG");
  TAKE(snd_pd, "SND_PD");
  TAKE(conn_status, "CONN_STATUS");
  TAKE(conn_size, "CONN_SIZE");
  TAKE(io_size, "IO_AREA_SIZE");
  TAKE(msg_max, "MSG_MAX_SIZE");
  TAKE(header, "TELEGRAM_HEADER_SIZE");
  TAKE(hostcom, "HOSTCOM");
  TAKE(devack, "DEVACK");
  TAKE(hostack, "HOSTACK");
  TAKE(devcom, "DEVCOM");
  TAKE(host_mbx, "HOST_MBX");
  TAKE(dev_mbx_bit, "DEV_MBX_BIT");
  TAKE(nak, "NAK");
  TAKE(ring, "RING");
  TAKE(plc_task, "PLC_TASK");
  TAKE(command, "COM_SHARED_MEMORY");
  TAKE(read, "READ");
  TAKE(write, "WRITE");
  TAKE(area_by_function, "AREA_BY_FUNCTION");
  TAKE(area_receive, "AREA_RECEIVE");
  TAKE(area_send, "AREA_SEND");
  TAKE(bit_type, "BIT");
  TAKE(uint16_type, "UINT16");
  TAKE(f_unknown_function, "UNKNOWN_FUNCTION");
  TAKE(f_unknown_data_type, "UNKNOWN_DATA_TYPE");
  TAKE(f_illegal_area, "ILLEGAL_AREA");
  TAKE(f_illegal_count, "ILLEGAL_COUNT");
  TAKE(f_overflow, "BUFFER_OVERFLOW");
  TAKE(can_task, "CAN_TASK");
  TAKE(com_sdo, "COM_SDO_UP_DOWNLOAD");
  TAKE(sdo_long_first, "SDO_LONG_FIRST");
  TAKE(task2_state, "TASK2_STATE");
  TAKE(task2_size, "TASK2_STATE_SIZE");
  n = PyTuple_GET_SIZE(types);
  if (n > MAX_TYPES) {
    PyErr_SetString(PyExc_ValueError, "configure: too many data types");
    return NULL;
  }
  for (i = 0; i < n; i++) {
    if (!PyArg_ParseTuple(PyTuple_GET_ITEM(types, i), "iii", &cfg.type_code[i],
                          &cfg.max_address[i], &cfg.max_count[i]))
      return NULL;
  }
  cfg.ntypes = (int)n;
  if (cfg.msg_max < 8 + cfg.header || cfg.msg_max > 8 + 255 || cfg.io_size <= 0 ||
      cfg.task2_size <= 0 || cfg.task2_size > 256) {
    PyErr_SetString(PyExc_ValueError, "configure: inconsistent sizes");
    return NULL;
  }
  cfg.ready = 1;
  Py_RETURN_NONE;
}

/* msg.f for a COM_Shared_Memory header that asks for too much, 0 when it is good: the
 * checks of firmware/plc.py's _check, in its order. */
static int check(int area, int adr, int idx, int cnt, int type, int function) {
  int t, width;
  long io = (long)cfg.io_size;
  if (function != cfg.read && function != cfg.write) return cfg.f_unknown_function;
  for (t = 0; t < cfg.ntypes && cfg.type_code[t] != type; t++) {
  }
  if (t == cfg.ntypes) return cfg.f_unknown_data_type;
  if (area != cfg.area_by_function && area != cfg.area_receive && area != cfg.area_send)
    return cfg.f_illegal_area;
  if (cnt < 1 || cnt > cfg.max_count[t]) return cfg.f_illegal_count;
  if (type == cfg.bit_type) {
    if (idx > 15) return cfg.f_overflow;
    if (adr > cfg.max_address[t] || (long)adr * 16 + idx + cnt > io * 8) return cfg.f_overflow;
    return 0;
  }
  width = type == cfg.uint16_type ? 2 : 1;
  if (adr > cfg.max_address[t] || ((long)adr + cnt) * width > io) return cfg.f_overflow;
  return 0;
}

/* Whether the request in raw is COM_Shared_Memory to the PLC task, the one message that
 * answer() may serve (and the one for which the turn takes the process image's lock). */
static int shared_memory_request(const unsigned char *raw) {
  return raw[0] == cfg.plc_task && raw[6] == cfg.command;
}

/* The answer to the request in raw (a copy of the slot) into out: its length, or 0 when
 * the request is not one this file answers (the Python turn does). inputs: the receive
 * area's bytes (the process image's inputs, under its lock). */
static Py_ssize_t answer(const unsigned char *raw, const unsigned char *image,
                         const unsigned char *inputs, unsigned char *out) {
  int ln = raw[2], f = 0, area, adr, idx, cnt, type, function, i;
  const unsigned char *data = raw + 8, *source;
  Py_ssize_t n = 0;
  if (!shared_memory_request(raw) || (raw[7] & cfg.nak)) return 0;
  if (ln < cfg.header) {
    f = cfg.f_illegal_count;
  } else {
    area = data[1];
    adr = data[2] | (data[3] << 8);
    idx = data[4];
    cnt = data[5];
    type = data[6];
    function = data[7];
    f = check(area, adr, idx, cnt, type, function);
    if (!f) {
      if (function != cfg.read) return 0; /* a write: the Python turn */
      if (area == cfg.area_by_function) area = cfg.area_receive;
      source = area == cfg.area_receive ? inputs : image + cfg.snd_pd;
      n = type == cfg.bit_type ? (cnt + 7) / 8 : (Py_ssize_t)cnt * (type == cfg.uint16_type ? 2 : 1);
      if (n + cfg.header > 255) return 0; /* no answer of the seed's sizes: the Python turn */
      memcpy(out + 8, data, (size_t)cfg.header);
      if (type != cfg.bit_type) {
        int width = type == cfg.uint16_type ? 2 : 1;
        memcpy(out + 8 + cfg.header, source + (Py_ssize_t)adr * width, (size_t)n);
      } else {
        long first = (long)adr * 16 + idx;
        memset(out + 8 + cfg.header, 0, (size_t)n);
        for (i = 0; i < cnt; i++) {
          long bit = first + i;
          if ((source[bit >> 3] >> (bit & 7)) & 1)
            out[8 + cfg.header + (i >> 3)] |= (unsigned char)(1u << (i & 7));
        }
      }
      n += cfg.header;
    }
  }
  out[0] = raw[1]; /* rx, tx swapped */
  out[1] = raw[0];
  out[2] = (unsigned char)n;
  out[3] = raw[3]; /* nr */
  out[4] = raw[6]; /* a = b */
  out[5] = (unsigned char)f;
  out[6] = 0;
  out[7] = 0;
  return 8 + n;
}

/* A host SDO request (COM_SDO_Up_Download to the CAN task, msg.e 0, or 4: a long upload's
 * request, or a long download's first part) [ours]: the message is taken as the Python
 * turn's _receive takes it (DEVACK toggled first) and handed to the CAN task's ``sdo``
 * callable (HostSdo.native_request) as bytes; its answer, when the transfer ended inside the
 * call with one answer (a long upload's value that fits one message), goes into the host
 * mailbox here; the several answers of a longer one are posted, as on the Python turn. 1: answered, out/len set; 0: the
 * message is not one for this path (the Python turn takes it, nothing changed); 2: taken,
 * its answer comes later (posted by the CAN task, as on the Python turn); -1: error.
 * Task2State is compared around the call: a change the call made in this thread rang no
 * one (Device._wake), so *changed asks for the Python turn, which shows it. */
static int sdo_turn(PyObject *sdo, const unsigned char *raw, unsigned char *mm,
                    unsigned char host, unsigned char *out, Py_ssize_t *len, int *changed) {
  unsigned char state[256];
  PyObject *got;
  Py_ssize_t n;
  if (sdo == Py_None || raw[0] != cfg.can_task || raw[6] != cfg.com_sdo ||
      (raw[7] != 0 && raw[7] != cfg.sdo_long_first) || 8 + (Py_ssize_t)raw[2] > cfg.msg_max)
    return 0;
  memcpy(state, mm + cfg.task2_state, (size_t)cfg.task2_size);
  __atomic_store_n(mm + cfg.host_flags, (unsigned char)(host ^ cfg.devack), __ATOMIC_SEQ_CST);
  got = PyObject_CallFunction(sdo, "y#", (const char *)raw, (Py_ssize_t)(8 + raw[2]));
  if (got == NULL) return -1;
  *changed = memcmp(state, mm + cfg.task2_state, (size_t)cfg.task2_size) != 0;
  if (got == Py_None) {
    Py_DECREF(got);
    return 2;
  }
  if (!PyBytes_Check(got) || (n = PyBytes_GET_SIZE(got)) < 8 || n > cfg.msg_max ||
      n != 8 + (Py_ssize_t)(unsigned char)PyBytes_AS_STRING(got)[2]) {
    Py_DECREF(got);
    PyErr_SetString(PyExc_ValueError, "serve: the SDO answer is no message");
    return -1;
  }
  memcpy(out, PyBytes_AS_STRING(got), (size_t)n);
  *len = n;
  Py_DECREF(got);
  return 1;
}

static double monotonic(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

/* A ring's sender as Python's socket module gives it: bytes for an abstract name, str for
 * a path, '' for an unnamed socket. */
static PyObject *sender(const struct sockaddr_un *addr, socklen_t len) {
  Py_ssize_t n = (Py_ssize_t)len - (Py_ssize_t)offsetof(struct sockaddr_un, sun_path);
  if (n <= 0) return PyUnicode_FromString("");
  if (addr->sun_path[0] == '\0') return PyBytes_FromStringAndSize(addr->sun_path, n);
  return PyUnicode_DecodeFSDefaultAndSize(addr->sun_path, (Py_ssize_t)strnlen(addr->sun_path, (size_t)n));
}

/* Ring every host (abstract names, bytes); the ones nobody listens at any more go to dead. */
static int ring_hosts(int fd, PyObject *hosts, PyObject *dead) {
  Py_ssize_t i, n = PyList_GET_SIZE(hosts);
  unsigned char payload = cfg.ring;
  for (i = 0; i < n; i++) {
    PyObject *host = PyList_GET_ITEM(hosts, i);
    struct sockaddr_un addr;
    Py_ssize_t len = PyBytes_GET_SIZE(host);
    memset(&addr, 0, sizeof addr);
    addr.sun_family = AF_UNIX;
    memcpy(addr.sun_path, PyBytes_AS_STRING(host), (size_t)len);
    if (sendto(fd, &payload, 1, MSG_DONTWAIT, (struct sockaddr *)&addr,
               (socklen_t)(offsetof(struct sockaddr_un, sun_path) + (size_t)len)) < 0 &&
        (errno == ECONNREFUSED || errno == ENOENT || errno == EPERM || errno == EACCES)) {
      if (PyList_Append(dead, host) < 0) return -1;
    }
  }
  return 0;
}

/* Take a lock (threading.Lock, RLock) without blocking: 1 taken, 0 busy, -1 error. */
static int try_lock(PyObject *lock) {
  PyObject *got = PyObject_CallMethod(lock, "acquire", "O", Py_False);
  int taken;
  if (got == NULL) return -1;
  taken = PyObject_IsTrue(got);
  Py_DECREF(got);
  return taken;
}

static int unlock(PyObject *lock) {
  PyObject *done = PyObject_CallMethod(lock, "release", NULL);
  if (done == NULL) return -1;
  Py_DECREF(done);
  return 0;
}

/* Whether the loop's queues and recording are as the caller left them (empty; the
 * recording it handed over, or none). */
static int device_quiet(PyObject *device, PyObject *recording_, PyObject *calls,
                        PyObject *outbox, PyObject *indications) {
  PyObject *recorder = PyObject_GetAttrString(device, "recorder");
  int quiet;
  if (recorder == NULL) return -1;
  quiet = recorder == recording_ && PyObject_Length(calls) == 0 &&
          PyObject_Length(outbox) == 0 && PyObject_Length(indications) == 0;
  Py_DECREF(recorder);
  return PyErr_Occurred() ? -1 : quiet;
}

/* --- Recording from the turn in C [ours] (issue 25) ----------------------------------------
 *
 * A recording card took the Python turn for every message until its recorder's hooks
 * (firmware/recorder.py: ``dev_flags``, ``put``, ``answer``) had seen it, which cost a
 * COM_Shared_Memory round trip 64-104 % more than a plain card's turn here. A turn served
 * here now records what those hooks record for it, in their order and with their clock:
 * the DevFlags it read at its start (when they changed since the recorder saw them last,
 * time stamped with the turn's start), the message it took with its DEVACK toggle and the
 * lines of the transaction ledger (read after the toggle, before the answer, as ``put``
 * reads them: the host's line is gone once it took the answer), and the answer with its
 * HOSTCOM toggle and Task2State (copied before the answer is written). The events are
 * packed by dpm/session.py's spool heads (their struct formats, handed over by
 * ``configure_record``: the layout lives there) and appended to the recorder's own queue,
 * the bytearray its hooks append to. Why that queue, and not a spool or ring of this
 * file's own: it is already where the card's events are put in order (the hooks of the
 * card's other threads append to it under the turn lock, as this does under the same
 * lock), its drain thread already hands it to the writer every 50 ms, and an append is a
 * resize and a copy under the interpreter lock this code holds anyway; a second stream
 * would need a merge by time stamp that neither the drain nor the writer does, and a
 * batch handed back to Python at the end of ``serve`` would hold events back from the
 * drain and from the hooks' order. The append is made after the ring: nothing can look
 * at the queue before this code lets go of the interpreter lock, and the host's answer
 * does not wait for it. A turn whose DevFlags ask for a start is left to the Python turn
 * (its event carries Task2Parameter, and the start is Python's).
 */

#define SPOOL_FORMAT_MAX 16
#define ANSWER_MAX (8 + 255) /* answer()'s out: the longest answer this file gives */

/* One event kind's head in the spool: dpm.session's struct format ('<' and the letters
 * B, H and d only), its size, and the kind's code. */
typedef struct {
  int code;
  Py_ssize_t size;
  char format[SPOOL_FORMAT_MAX];
} spool_head;

/* What configure_record() took from dpm/ and firmware/recorder.py. */
static struct {
  int ready;
  spool_head put, answer, dev_flags;
  Py_ssize_t ln_offset, msg_header, ledger_first, ledger_bytes;
  unsigned char end, starts;
  unsigned char *scratch; /* one turn's events, packed before they are appended */
  Py_ssize_t scratch_size;
} rec;

/* One served turn's recording, as serve() gathers it. */
typedef struct {
  PyObject *recorder; /* the recording the turn records for; Py_None: none */
  PyObject *queue;    /* its queue (bytearray) */
  int ledger;         /* its descriptor of the transaction ledger */
  int dev;            /* DevFlags as the recorder saw them last */
  double t_turn;      /* the turn's start, the clock read its DevFlags event takes */
  unsigned char dev_now;
  Py_ssize_t used;    /* bytes of rec.scratch this turn packed */
} recording;

PyDoc_STRVAR(configure_record_doc,
             "configure_record(spool: dict[str, object])\n\n"
             "What the turn in C records with, by name: per event kind (PUT, ANSWER, DEV_FLAGS)\n"
             "its code and dpm.session's struct format and size; Task2State's offset and size;\n"
             "the message's header size, msg.ln's offset and the slot's size; the recorder's\n"
             "two ledger reads and the ledger's END byte; DevFlags' start bits; DEVACK and HOSTCOM.");

/* Size of a head of format, or -1 when it is not '<' followed by fields letters of B, H and
 * d, the code first (B) and t second (d). */
static Py_ssize_t head_size(const char *format, int fields) {
  Py_ssize_t size = 0;
  int n = 0;
  const char *c;
  if (format[0] != '<') return -1;
  for (c = format + 1; *c; c++, n++) {
    if (*c == 'B') size += 1;
    else if (*c == 'H') size += 2;
    else if (*c == 'd') size += 8;
    else return -1;
    if ((n == 0 && *c != 'B') || (n == 1 && *c != 'd')) return -1;
  }
  return n == fields ? size : -1;
}

static int take_head(PyObject *spool, const char *name, int fields, spool_head *head) {
  PyObject *item = PyDict_GetItemString(spool, name); /* borrowed */
  const char *format;
  Py_ssize_t length;
  if (item == NULL) {
    PyErr_Format(PyExc_KeyError, "configure_record: %s missing", name);
    return -1;
  }
  if (!PyArg_ParseTuple(item, "is#n", &head->code, &format, &length, &head->size)) return -1;
  if (length >= SPOOL_FORMAT_MAX || head->code < 0 || head->code > 255 ||
      head_size(format, fields) != head->size) {
    PyErr_Format(PyExc_ValueError, "configure_record: %s's head is not one this file packs", name);
    return -1;
  }
  memcpy(head->format, format, (size_t)length + 1);
  return 0;
}

#define TAKE_RECORD(field, name) TAKE_INTO(spool, rec.field, name)

static PyObject *configure_record(PyObject *self, PyObject *args) {
  PyObject *spool;
  (void)self;
  if (!PyArg_ParseTuple(args, "O!", &PyDict_Type, &spool)) return NULL;
  if (!cfg.ready) { /* the layout's sizes, bits and Task2State come from configure() */
    PyErr_SetString(PyExc_RuntimeError, "configure() first");
    return NULL;
  }
  rec.ready = 0;
  if (take_head(spool, "PUT", 6, &rec.put) < 0 || take_head(spool, "ANSWER", 5, &rec.answer) < 0 ||
      take_head(spool, "DEV_FLAGS", 5, &rec.dev_flags) < 0)
    return NULL;
  TAKE_RECORD(ln_offset, "LN_OFFSET");
  TAKE_RECORD(msg_header, "MSG_HEADER_SIZE");
  TAKE_RECORD(ledger_first, "LEDGER_FIRST_READ");
  TAKE_RECORD(ledger_bytes, "LEDGER_BYTES");
  TAKE_RECORD(end, "END");
  TAKE_RECORD(starts, "STARTS");
  if (rec.ln_offset < 0 || rec.ln_offset >= rec.msg_header || cfg.msg_max < rec.msg_header ||
      rec.ledger_first <= 0 || rec.ledger_bytes < rec.ledger_first || rec.ledger_bytes > 0xFFFF) {
    PyErr_SetString(PyExc_ValueError, "configure_record: inconsistent sizes");
    return NULL;
  }
  PyMem_Free(rec.scratch);
  rec.scratch_size = rec.dev_flags.size + rec.put.size + cfg.msg_max + rec.ledger_bytes +
                     rec.answer.size + ANSWER_MAX + cfg.task2_size;
  rec.scratch = PyMem_Malloc((size_t)rec.scratch_size);
  if (rec.scratch == NULL) return PyErr_NoMemory();
  rec.ready = 1;
  Py_RETURN_NONE;
}

/* A clock read as time.monotonic() makes it (CLOCK_MONOTONIC in nanoseconds, then seconds
 * rounded as CPython rounds them): the hooks' time stamps and these are one clock. */
static double record_clock(void) {
  struct timespec ts;
  long long ns;
  volatile double d;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  ns = (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
  if (ns % 1000000000LL == 0) {
    d = (double)(ns / 1000000000LL);
  } else {
    d = (double)ns;
    d /= 1e9;
  }
  return d;
}

/* Pack a head of head's format from values (the code, t, then its fields) at out. */
static void pack_head(const spool_head *head, const double *values, unsigned char *out) {
  const char *c;
  Py_ssize_t n = 0;
  int i = 0;
  for (c = head->format + 1; *c; c++, i++) {
    if (*c == 'd') {
      PyFloat_Pack8(values[i], (char *)out + n, 1);
      n += 8;
    } else {
      unsigned long v = (unsigned long)values[i];
      out[n++] = (unsigned char)(v & 0xFF);
      if (*c == 'H') out[n++] = (unsigned char)((v >> 8) & 0xFF);
    }
  }
}

/* serve()'s last argument: None, or (recorder, queue, ledger, dev) from
 * Recorder.native_record(). 0 done, -1 error. */
static int record_open(PyObject *arg, recording *r) {
  r->recorder = Py_None;
  r->queue = NULL;
  r->ledger = -1;
  r->dev = 0;
  r->used = 0;
  if (arg == Py_None) return 0;
  if (!rec.ready) {
    PyErr_SetString(PyExc_RuntimeError, "configure_record() first");
    return -1;
  }
  if (!PyArg_ParseTuple(arg, "OO!ii", &r->recorder, &PyByteArray_Type, &r->queue, &r->ledger,
                        &r->dev))
    return -1;
  return 0;
}

/* Whether the turn may be recorded here: not one whose DevFlags ask for a start. */
static int record_allows(const recording *r, unsigned char dev) {
  return r->recorder == Py_None || (dev & rec.starts) == 0;
}

/* The turn's start, once it is known to be served here: its clock read and DevFlags, and
 * the DevFlags event when they changed (``Recorder.dev_flags``). */
static void record_turn(recording *r, unsigned char dev) {
  double values[5];
  r->used = 0;
  r->dev_now = dev;
  if (r->recorder == Py_None || dev == r->dev) return;
  values[0] = rec.dev_flags.code;
  values[1] = r->t_turn;
  values[2] = r->dev;
  values[3] = dev;
  values[4] = 0; /* no Task2Parameter: a start is the Python turn's (record_allows) */
  pack_head(&rec.dev_flags, values, rec.scratch);
  r->used = rec.dev_flags.size;
}

/* The message taken, after its DEVACK toggle from before (``Recorder.put``): the clock, the
 * ledger's lines up to END (the first read; all of it when that was not all), the message
 * as far as its msg.ln reaches. -1: the ledger could not be read (OSError set). */
static int record_put(recording *r, const unsigned char *raw, unsigned char before) {
  double values[6];
  unsigned char *head, *lines;
  Py_ssize_t msg, got, n;
  const void *end;
  if (r->recorder == Py_None) return 0;
  values[1] = record_clock();
  msg = rec.msg_header + raw[rec.ln_offset];
  if (msg > cfg.msg_max) msg = cfg.msg_max;
  head = rec.scratch + r->used;
  lines = head + rec.put.size + msg;
  got = pread(r->ledger, lines, (size_t)rec.ledger_first, 0);
  if (got < 0) {
    PyErr_SetFromErrno(PyExc_OSError);
    return -1;
  }
  end = memchr(lines, rec.end, (size_t)got);
  if (end == NULL && got == rec.ledger_first) {
    got = pread(r->ledger, lines, (size_t)rec.ledger_bytes, 0);
    if (got < 0) {
      PyErr_SetFromErrno(PyExc_OSError);
      return -1;
    }
    end = memchr(lines, rec.end, (size_t)got);
  }
  n = end != NULL ? (const unsigned char *)end - lines : got;
  values[0] = rec.put.code;
  values[2] = before;
  values[3] = before ^ cfg.devack;
  values[4] = (double)msg;
  values[5] = (double)n;
  pack_head(&rec.put, values, head);
  memcpy(head + rec.put.size, raw, (size_t)msg);
  r->used += rec.put.size + msg + n;
  return 0;
}

/* The answer, before it is written, with the HOSTCOM toggle from before that hands it over
 * (``Recorder.answer``): the clock, the answer's bytes, Task2State as the image holds it. */
static void record_answer(recording *r, const unsigned char *out, Py_ssize_t len,
                          unsigned char before, const unsigned char *image) {
  double values[5];
  unsigned char *head;
  if (r->recorder == Py_None) return;
  values[0] = rec.answer.code;
  values[1] = record_clock();
  values[2] = before;
  values[3] = before ^ cfg.hostcom;
  values[4] = (double)len;
  head = rec.scratch + r->used;
  pack_head(&rec.answer, values, head);
  memcpy(head + rec.answer.size, out, (size_t)len);
  memcpy(head + rec.answer.size + len, image + cfg.task2_state, (size_t)cfg.task2_size);
  r->used += rec.answer.size + len + cfg.task2_size;
}

/* The turn's events onto the recorder's queue, in one append, as a hook's ``+=``. */
static int record_commit(recording *r) {
  Py_ssize_t had;
  if (r->recorder == Py_None) return 0;
  had = PyByteArray_GET_SIZE(r->queue);
  if (PyByteArray_Resize(r->queue, had + r->used) < 0) return -1;
  memcpy(PyByteArray_AS_STRING(r->queue) + had, rec.scratch, (size_t)r->used);
  r->dev = r->dev_now;
  r->used = 0;
  return 0;
}

/* --- The process-data exchange in C [ours] (issue 25) ------------------------------------
 *
 * A host in the buffered host-controlled mode (exchange mode 4) toggles PDCOM and rings for every
 * DevExchangeIO; the Python turn answered each (PlcTask.service: ProcessImage.cycle, the
 * PDACK toggle) with its recorder's three hooks on a recording card (``dev_flags``,
 * ``host_flags``, ``settle``), which cost that card 8-11 us more CPU per exchange than a
 * plain one, and the exchange loop's p50 more than issue 25's 10 % in two of five runs
 * (docs/benchmarks.md, note 8). Here the turn serves such an exchange when it changes
 * nothing the CAN master follows: the host's SndPd as the last exchange took it (the
 * process image's ``outputs``; a new output is the Python turn's, whose ``notice_host``
 * sends it), no input bit flipped (the fault "flip"), no message pending beside it, READY
 * and the special-control bits as the Python turn would leave them. It copies the inputs
 * into RcvPd when they changed (as ``cycle``, under the process image's lock, and tells
 * ``exchanged_changes``), toggles PDACK, rings, and for a recording card appends the events
 * the hooks would have queued (after the ring, as ``settle``): the host's PD toggle with
 * the turn's clock, then the exchange with its PDACK toggle, both areas when
 * ``exchanged_changes`` says they may have changed since the recording last took them, and
 * Task2State. Kept apart from the mailbox's turn above: serve() asks these functions. */

/* What configure_exchange() took from dpm/. */
static struct {
  int ready;
  unsigned char pd, pdack, ready_bit, spc;
  Py_ssize_t rcv_pd;
  spool_head head;        /* the exchange's spool head (dpm.session.SPOOL_EXCHANGE) */
  unsigned char *scratch; /* one exchange's events, packed before they are appended */
} xcfg;

/* serve()'s exchange argument: None, or (process image, its outputs bytearray). */
typedef struct {
  PyObject *image;   /* NULL: no exchange served here */
  PyObject *outputs; /* ProcessImage.outputs: SndPd as the last exchange took it */
} exchange;

PyDoc_STRVAR(configure_exchange_doc,
             "configure_exchange(numbers: dict[str, object])\n\n"
             "The exchange's flag bits (PD, PDACK, READY, SPC), RcvPd's offset and the spool\n"
             "head of an exchange (EXCHANGE: code, struct format, size), by name; after\n"
             "configure() and configure_record().");

static PyObject *configure_exchange(PyObject *self, PyObject *args) {
  PyObject *numbers;
  (void)self;
  if (!PyArg_ParseTuple(args, "O!", &PyDict_Type, &numbers)) return NULL;
  if (!cfg.ready || !rec.ready) {
    PyErr_SetString(PyExc_RuntimeError, "configure() and configure_record() first");
    return NULL;
  }
  xcfg.ready = 0;
  TAKE_INTO(numbers, xcfg.pd, "PD");
  TAKE_INTO(numbers, xcfg.pdack, "PDACK");
  TAKE_INTO(numbers, xcfg.ready_bit, "READY");
  TAKE_INTO(numbers, xcfg.spc, "SPC");
  TAKE_INTO(numbers, xcfg.rcv_pd, "RCV_PD");
  if (take_head(numbers, "EXCHANGE", 5, &xcfg.head) < 0) return NULL;
  if (xcfg.rcv_pd < 0) {
    PyErr_SetString(PyExc_ValueError, "configure_exchange: inconsistent sizes");
    return NULL;
  }
  PyMem_Free(xcfg.scratch);
  xcfg.scratch = PyMem_Malloc((size_t)(rec.dev_flags.size + xcfg.head.size + 2 * cfg.io_size +
                                       cfg.task2_size));
  if (xcfg.scratch == NULL) return PyErr_NoMemory();
  xcfg.ready = 1;
  Py_RETURN_NONE;
}

/* serve()'s exchange argument into x. 0 done, -1 error. */
static int exchange_open(PyObject *arg, exchange *x, Py_ssize_t image_len) {
  x->image = NULL;
  x->outputs = NULL;
  if (arg == NULL || arg == Py_None) return 0;
  if (!xcfg.ready) {
    PyErr_SetString(PyExc_RuntimeError, "configure_exchange() first");
    return -1;
  }
  if (!PyArg_ParseTuple(arg, "OO!", &x->image, &PyByteArray_Type, &x->outputs)) return -1;
  if (PyByteArray_GET_SIZE(x->outputs) != cfg.io_size || image_len < xcfg.rcv_pd + cfg.io_size) {
    PyErr_SetString(PyExc_ValueError, "serve: the exchange's areas do not fit the layout");
    return -1;
  }
  return 0;
}

/* The DevFlags bits a served exchange may have changed since serve() began: PDCOM. */
static unsigned char exchange_toggles(const exchange *x) {
  return x->image != NULL ? xcfg.pd : 0;
}

enum { EXCHANGE_NONE, EXCHANGE_HERE, EXCHANGE_PYTHON };

/* Whether the host asks for an exchange at these flags (host-controlled: its PD toggle),
 * and whether this file may serve it: no message pending beside it (the Python turn takes
 * the message first), READY up, SPCACK as the Python turn leaves it. */
static int exchange_state(const exchange *x, unsigned char dev, unsigned char host) {
  if (x->image == NULL || !((host ^ dev) & xcfg.pd)) return EXCHANGE_NONE;
  if (((host ^ dev) & cfg.dev_mbx_bit) || !(host & xcfg.ready_bit) || ((host ^ dev) & xcfg.spc))
    return EXCHANGE_PYTHON;
  return EXCHANGE_HERE;
}

/* A Python attribute's truth: 1, 0, -1 error. */
static int attribute_true(PyObject *object, const char *name) {
  PyObject *value = PyObject_GetAttrString(object, name);
  int truth;
  if (value == NULL) return -1;
  truth = PyObject_IsTrue(value);
  Py_DECREF(value);
  return truth;
}

/* The exchange's events onto the recorder's queue (``Recorder.dev_flags`` and ``settle``):
 * DevFlags when they changed since the recorder saw them (the turn's clock), the exchange
 * with its PDACK toggle from host, the areas when ``exchanged_changes`` says so, Task2State.
 * 0 done, -1 error. */
static int exchange_record(const exchange *x, recording *r, const unsigned char *mm,
                           unsigned char dev, unsigned char host) {
  double values[5];
  unsigned char *out = xcfg.scratch;
  Py_ssize_t used = 0, had;
  int changed;
  if (r->recorder == Py_None) return 0;
  changed = attribute_true(x->image, "exchanged_changes");
  if (changed < 0) return -1;
  if (dev != r->dev) {
    values[0] = rec.dev_flags.code;
    values[1] = r->t_turn;
    values[2] = r->dev;
    values[3] = dev;
    values[4] = 0; /* no Task2Parameter: a start is the Python turn's (record_allows) */
    pack_head(&rec.dev_flags, values, out);
    used = rec.dev_flags.size;
  }
  values[0] = xcfg.head.code;
  values[1] = record_clock();
  values[2] = host;
  values[3] = host ^ xcfg.pdack;
  values[4] = changed;
  pack_head(&xcfg.head, values, out + used);
  used += xcfg.head.size;
  if (changed) {
    memcpy(out + used, PyByteArray_AS_STRING(x->outputs), (size_t)cfg.io_size);
    memcpy(out + used + cfg.io_size, mm + xcfg.rcv_pd, (size_t)cfg.io_size);
    used += 2 * cfg.io_size;
    if (PyObject_SetAttrString(x->image, "exchanged_changes", Py_False) < 0) return -1;
  }
  memcpy(out + used, mm + cfg.task2_state, (size_t)cfg.task2_size);
  used += cfg.task2_size;
  had = PyByteArray_GET_SIZE(r->queue);
  if (PyByteArray_Resize(r->queue, had + used) < 0) return -1;
  memcpy(PyByteArray_AS_STRING(r->queue) + had, out, (size_t)used);
  r->dev = dev;
  return 0;
}

/* Serve the exchange the host asks for (exchange_state said EXCHANGE_HERE), holding the turn
 * lock: 1 served (rung, recorded), 0 left to the Python turn (nothing changed), -1 error. */
static int exchange_turn(const exchange *x, recording *r, unsigned char *mm, unsigned char dev,
                         unsigned char host, PyObject *inputs, PyObject *image_lock, int fd,
                         PyObject *hosts, PyObject *dead) {
  int locked = try_lock(image_lock), flipped, copied = 0;
  if (locked <= 0) return locked;
  flipped = attribute_true(x->image, "_flips");
  if (flipped != 0 ||
      memcmp(mm + cfg.snd_pd, PyByteArray_AS_STRING(x->outputs), (size_t)cfg.io_size) != 0) {
    if (unlock(image_lock) < 0 || flipped < 0) return -1;
    return 0; /* a flipped bit or new outputs: the Python turn */
  }
  if (memcmp(mm + xcfg.rcv_pd, PyByteArray_AS_STRING(inputs), (size_t)cfg.io_size) != 0) {
    memcpy(mm + xcfg.rcv_pd, PyByteArray_AS_STRING(inputs), (size_t)cfg.io_size);
    copied = 1;
  }
  if (unlock(image_lock) < 0) return -1;
  if (copied && PyObject_SetAttrString(x->image, "exchanged_changes", Py_True) < 0) return -1;
  __atomic_store_n(mm + cfg.host_flags, (unsigned char)(host ^ xcfg.pdack), __ATOMIC_SEQ_CST);
  if (ring_hosts(fd, hosts, dead) < 0) return -1;
  if (exchange_record(x, r, mm, dev, host) < 0) return -1; /* after the ring, as settle */
  return 1;
}

PyDoc_STRVAR(serve_doc,
             "serve(image, fd, hosts, interval, due, device, calls, outbox, indications,\n"
             "      turn, image_lock, inputs, outputs, conn, record, sdo[, exchange]) -> (rings,\n"
             "      dead, turns, dev_seen, watchdog_seen, host_seen, recorded_dev)\n\n"
             "Answer the last of hosts' COM_Shared_Memory reads, and hand its\n"
             "COM_SDO_Up_Download requests (msg.e 0, 4) to sdo (None: not now), until a turn\n"
             "needs Python.\n"
             "image: the board's mmap; fd: the device bell; hosts: the known hosts' abstract\n"
             "names, the expected one last; interval: the poll interval, due: the watchdog's\n"
             "deadline plus the loop's lateness (monotonic seconds, or a negative number);\n"
             "device, calls, outbox, indications: looked at each turn (recorder, queues);\n"
             "turn, image_lock: the device's turn lock and the process image's lock, each\n"
             "taken without blocking; inputs: the image's receive area (bytearray); outputs:\n"
             "the output area the CAN master saw last; conn: the connection bits it saw;\n"
             "record: None, or the recording's (recorder, queue, ledger, dev), whose events\n"
             "each served turn appends to queue; sdo: HostSdo.native_request or None (not\n"
             "taken while recording). Returns the rings taken that need the Python turn,\n"
             "the hosts that are gone, the turns served, DevFlags, the watchdog trigger and\n"
             "HostFlags as the last served turn left them, and the DevFlags the recording\n"
             "saw last (-1: none). exchange: None (the default), or (the process image,\n"
             "its outputs bytearray) in a host-controlled mode: the host's exchanges that\n"
             "change no output are served here too, and recorded (configure_exchange).");

static PyObject *serve(PyObject *self, PyObject *args) {
  Py_buffer image, outputs, conn;
  int fd, turns = 0, failed = 0;
  double interval, due;
  PyObject *hosts, *device, *calls, *outbox, *indications, *turn, *image_lock, *inputs, *sdo;
  PyObject *rings = NULL, *dead = NULL, *expected, *result = NULL, *record, *exchange_arg = NULL;
  recording r;
  exchange x;
  unsigned char *mm, dev_base, watchdog, dev_seen = 0, watchdog_seen = 0, host_seen = 0;
  (void)self;
  if (!cfg.ready) {
    PyErr_SetString(PyExc_RuntimeError, "configure() first");
    return NULL;
  }
  if (!PyArg_ParseTuple(args, "w*iO!ddOOOOOOO!y*y*OO|O", &image, &fd, &PyList_Type, &hosts,
                        &interval, &due, &device, &calls, &outbox, &indications, &turn,
                        &image_lock, &PyByteArray_Type, &inputs, &outputs, &conn, &record,
                        &sdo, &exchange_arg))
    return NULL;
  mm = (unsigned char *)image.buf;
  if (record_open(record, &r) < 0 || exchange_open(exchange_arg, &x, image.len) < 0) goto done;
  if (image.len < cfg.snd_pd + cfg.io_size || image.len < cfg.dev_mbx + cfg.msg_max ||
      image.len < cfg.pc_mbx + cfg.msg_max || image.len < cfg.conn_status + cfg.conn_size ||
      image.len < cfg.task2_state + cfg.task2_size || (sdo != Py_None && !PyCallable_Check(sdo)) ||
      image.len <= cfg.host_flags || image.len <= cfg.dev_flags ||
      image.len <= cfg.dev_watchdog || outputs.len != cfg.io_size || conn.len != cfg.conn_size ||
      PyByteArray_GET_SIZE(inputs) != cfg.io_size || PyList_GET_SIZE(hosts) == 0) {
    PyErr_SetString(PyExc_ValueError, "serve: sizes do not fit the layout");
    goto done;
  }
  for (Py_ssize_t i = 0; i < PyList_GET_SIZE(hosts); i++) {
    PyObject *host = PyList_GET_ITEM(hosts, i);
    if (!PyBytes_Check(host) || PyBytes_GET_SIZE(host) < 1 || PyBytes_AS_STRING(host)[0] != 0 ||
        (size_t)PyBytes_GET_SIZE(host) > sizeof(((struct sockaddr_un *)0)->sun_path)) {
      PyErr_SetString(PyExc_ValueError, "serve: hosts are abstract names (bytes)");
      goto done;
    }
  }
  expected = PyList_GET_ITEM(hosts, PyList_GET_SIZE(hosts) - 1);
  rings = PyList_New(0);
  dead = PyList_New(0);
  if (rings == NULL || dead == NULL) goto done;
  dev_base = __atomic_load_n(mm + cfg.dev_flags, __ATOMIC_ACQUIRE);
  watchdog = mm[cfg.dev_watchdog];
  for (;;) {
    unsigned char payload[16], raw[8 + 255], out[8 + 255], dev, host;
    struct sockaddr_un addr;
    socklen_t addrlen = sizeof addr;
    ssize_t got;
    Py_ssize_t len;
    double wait = interval;
    int ready, taken, quiet, sdo_kind = 0, changed = 0, exchanged = 0, pending;
    /* the clock only for a watchdog's deadline: each reading is a system call inside
     * User-Mode Linux (no vDSO), issue 22 */
    if (due >= 0) {
      double left = due - monotonic();
      if (left < wait) wait = left;
    }
    if (wait <= 0) break; /* the watchdog is due: the Python turn */
    Py_BEGIN_ALLOW_THREADS;
    {
      struct pollfd p = {fd, POLLIN, 0};
      struct timespec ts;
      ts.tv_sec = (time_t)wait;
      ts.tv_nsec = (long)((wait - (double)ts.tv_sec) * 1e9);
      ready = ppoll(&p, 1, &ts, NULL);
      got = ready > 0 ? recvfrom(fd, payload, sizeof payload, MSG_DONTWAIT,
                                 (struct sockaddr *)&addr, &addrlen)
                      : -1;
    }
    Py_END_ALLOW_THREADS;
    if (ready < 0 && errno != EINTR) {
      PyErr_SetFromErrno(PyExc_OSError);
      goto done;
    }
    if (ready < 0) {
      if (PyErr_CheckSignals() < 0) goto done;
      break; /* a signal: its handler may have asked the loop to stop */
    }
    if (ready == 0) break; /* the poll's interval: the Python turn */
    if (got < 0) continue; /* another thread took the ring */
    {
      PyObject *who = sender(&addr, addrlen);
      int same;
      if (who == NULL) goto done;
      same = got == 1 && payload[0] == cfg.ring && PyBytes_Check(who) &&
             PyBytes_GET_SIZE(who) == PyBytes_GET_SIZE(expected) &&
             memcmp(PyBytes_AS_STRING(who), PyBytes_AS_STRING(expected),
                    (size_t)PyBytes_GET_SIZE(who)) == 0;
      if (!same) {
        PyObject *ring = Py_BuildValue("(y#N)", (const char *)payload, (Py_ssize_t)got, who);
        if (ring == NULL || PyList_Append(rings, ring) < 0) {
          Py_XDECREF(ring);
          goto done;
        }
        Py_DECREF(ring);
        break;
      }
      Py_DECREF(who);
    }
    /* The expected host's plain ring: serve the turn here if it is a plain one. */
    taken = try_lock(turn);
    if (taken < 0) goto done;
    quiet = 0;
    len = 0;
    if (taken) {
      if (r.recorder != Py_None) r.t_turn = record_clock(); /* the Python turn's ``now`` */
      quiet = device_quiet(device, r.recorder, calls, outbox, indications);
      if (quiet < 0) {
        unlock(turn);
        goto done;
      }
    }
    if (quiet) {
      dev = __atomic_load_n(mm + cfg.dev_flags, __ATOMIC_ACQUIRE);
      host = mm[cfg.host_flags];
      pending = exchange_state(&x, dev, host);
      quiet = ((dev ^ dev_base) & ~(cfg.devcom | cfg.hostack | exchange_toggles(&x))) == 0 &&
              mm[cfg.dev_watchdog] == watchdog && pending != EXCHANGE_PYTHON &&
              (pending == EXCHANGE_HERE ||
               (((host ^ dev) & cfg.host_mbx) == 0 && ((host ^ dev) & cfg.dev_mbx_bit) != 0)) &&
              memcmp(mm + cfg.snd_pd, outputs.buf, (size_t)cfg.io_size) == 0 &&
              memcmp(mm + cfg.conn_status, conn.buf, (size_t)cfg.conn_size) == 0 &&
              record_allows(&r, dev) && (due < 0 || monotonic() <= due);
      if (quiet && pending == EXCHANGE_HERE) { /* the process-data exchange (above) */
        quiet = 0;
        exchanged = exchange_turn(&x, &r, mm, dev, host, inputs, image_lock, fd, hosts, dead);
        if (exchanged < 0) {
          failed = 1;
          exchanged = 0;
        }
        if (exchanged) {
          turns++;
          dev_seen = __atomic_load_n(mm + cfg.dev_flags, __ATOMIC_ACQUIRE);
          watchdog_seen = mm[cfg.dev_watchdog];
          host_seen = mm[cfg.host_flags];
        }
      }
      if (quiet) {
        int locked;
        memcpy(raw, mm + cfg.dev_mbx, (size_t)cfg.msg_max); /* one copy, as _receive */
        /* the process image's lock only for what answer() may serve: CPython's RLock reads
         * the clock on every acquire, a system call inside User-Mode Linux (issue 22) */
        locked = shared_memory_request(raw) ? try_lock(image_lock) : 0;
        if (locked < 0) failed = 1;
        if (locked > 0) {
          len = answer(raw, mm, (const unsigned char *)PyByteArray_AS_STRING(inputs), out);
          if (unlock(image_lock) < 0) failed = 1;
        }
        if (len == 0 && !failed && r.recorder == Py_None) {
          sdo_kind = sdo_turn(sdo, raw, mm, host, out, &len, &changed);
          if (sdo_kind < 0) failed = 1;
        }
        if (len > 0 && !sdo_kind) { /* sdo_turn took the message (DEVACK) before its call */
          record_turn(&r, dev);
          __atomic_store_n(mm + cfg.host_flags, (unsigned char)(host ^ cfg.devack),
                           __ATOMIC_SEQ_CST);
          if (record_put(&r, raw, host) < 0) { /* as an OSError of the hook's pread */
            failed = 1;
            len = 0;
          }
        }
        if (len > 0 || sdo_kind == 2) {
          if (len > 0) {
            record_answer(&r, out, len, (unsigned char)(host ^ cfg.devack), mm);
            memcpy(mm + cfg.pc_mbx, out, (size_t)len);
            __atomic_store_n(mm + cfg.host_flags,
                             (unsigned char)(host ^ cfg.devack ^ cfg.hostcom), __ATOMIC_SEQ_CST);
            if (ring_hosts(fd, hosts, dead) < 0) failed = 1;
            if (record_commit(&r) < 0) failed = 1; /* after the ring: the host waits not */
          }
          turns++;
          dev_seen = __atomic_load_n(mm + cfg.dev_flags, __ATOMIC_ACQUIRE);
          watchdog_seen = mm[cfg.dev_watchdog];
          host_seen = mm[cfg.host_flags];
        }
      }
    }
    if (taken) { /* an error of the turn stays the one raised: release() runs without it */
      PyObject *kind, *value, *trace;
      PyErr_Fetch(&kind, &value, &trace);
      if (unlock(turn) < 0) failed = 1;
      if (kind != NULL) PyErr_Restore(kind, value, trace);
    }
    /* A signal delivered to another thread leaves its handler pending for this one, which
     * the interpreter would run between two Python turns; a stop it asks for rings. */
    if (failed || PyErr_CheckSignals() < 0) goto done;
    /* A request sdo_turn took whose answer comes later is served: the answer is posted
     * (Device.hand_over) by the thread that ends the transfer, as after a Python turn. */
    if ((len == 0 && sdo_kind != 2 && !exchanged) || changed || PyList_GET_SIZE(dead) > 0) {
      /* the ring goes to the Python turn, which serves the message (not one sdo_turn took;
       * after one that changed Task2State the Python turn shows the change) */
      if (len == 0 && !sdo_kind && !exchanged) {
        PyObject *ring = Py_BuildValue("(y#O)", (const char *)payload, (Py_ssize_t)got, expected);
        if (ring == NULL || PyList_Append(rings, ring) < 0) {
          Py_XDECREF(ring);
          goto done;
        }
        Py_DECREF(ring);
      }
      break;
    }
  }
  result = Py_BuildValue("(OOiiiii)", rings, dead, turns, dev_seen, watchdog_seen, host_seen,
                         r.recorder == Py_None ? -1 : r.dev);
done:
  Py_XDECREF(rings);
  Py_XDECREF(dead);
  PyBuffer_Release(&image);
  PyBuffer_Release(&outputs);
  PyBuffer_Release(&conn);
  return result;
}

static PyMethodDef methods[] = {
    {"configure", configure, METH_VARARGS, configure_doc},
    {"configure_record", configure_record, METH_VARARGS, configure_record_doc},
    {"configure_exchange", configure_exchange, METH_VARARGS, configure_exchange_doc},
    {"serve", serve, METH_VARARGS, serve_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "firmware._mailbox",
    "The device loop's mailbox turn for a plain COM_Shared_Memory read, in C [ours].", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__mailbox(void) { return PyModule_Create(&module); }
