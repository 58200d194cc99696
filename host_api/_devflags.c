/*
 * host_api._devflags - DevFlags changed by one atomic read-modify-write on the mapped byte,
 * and the host's side of the doorbell in one call each.
 *
 * [ours] Every host process writes DevFlags (a put toggles DEVCOM, a get HOSTACK, an
 * exchange PDCOM, DevSetHostState NOTREADY ...), Python and C hosts (libcif) alike. A
 * plain read-modify-write from two processes could lose one host's toggle; an flock
 * around it (board<N>.flags.lock until issue 22) cost four system calls per mailbox round
 * trip. A compare-and-swap on the byte itself excludes nobody and costs none; libcif's
 * change_dev_flags does the same (libcif/src/cif_api.c), so the two drivers share a card.
 *
 * [ours] ``change_ring`` and ``wait_ring`` are the doorbell's host side (dpm/doorbell.py,
 * docs/dpm.md section 2) on the path of every mailbox round trip: the toggle and its ring
 * in one call instead of four Python calls, and a wait (ppoll) that takes every queued ring in
 * one recvmmsg instead of select, recvfrom and a second select (issue 22).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h> /* pyconfig.h defines _GNU_SOURCE: recvmmsg */

#include <errno.h>
#include <math.h>
#include <poll.h>
#include <stddef.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <time.h>
#include <unistd.h>

#define RINGS_AT_ONCE 16
/* Rings one wait takes at most; the device sends one per change, and a host's queue holds
 * /proc/sys/net/unix/max_dgram_qlen (10 by default). */

static unsigned char change_byte(unsigned char *p, unsigned char set, unsigned char clear,
                                 unsigned char toggle) {
  unsigned char old = __atomic_load_n(p, __ATOMIC_RELAXED), new;
  do {
    new = (unsigned char)(((old | set) & ~clear) ^ toggle);
    /* seq_cst: what the host wrote before (a message in DevMbx) is seen before the bit */
  } while (!__atomic_compare_exchange_n(p, &old, new, 0, __ATOMIC_SEQ_CST, __ATOMIC_RELAXED));
  return new;
}

PyDoc_STRVAR(change_doc,
             "change(image, offset, set_bits, clear_bits, toggle) -> int\n\n"
             "Set, clear, then toggle bits of the byte at offset of the writable buffer\n"
             "image (the board's mmap), atomically across processes; the new value.");

static PyObject *change(PyObject *self, PyObject *args) {
  Py_buffer image;
  Py_ssize_t offset;
  unsigned char set, clear, toggle, new;
  (void)self;
  if (!PyArg_ParseTuple(args, "w*nbbb", &image, &offset, &set, &clear, &toggle)) return NULL;
  if (offset < 0 || offset >= image.len) {
    PyBuffer_Release(&image);
    PyErr_SetString(PyExc_IndexError, "offset outside the image");
    return NULL;
  }
  new = change_byte((unsigned char *)image.buf + offset, set, clear, toggle);
  PyBuffer_Release(&image);
  return PyLong_FromLong(new);
}

PyDoc_STRVAR(change_ring_doc,
             "change_ring(image, offset, set_bits, clear_bits, toggle, fd, address, payload)"
             " -> int\n\n"
             "change(), then send the one-byte datagram payload from the socket fd to the\n"
             "file system socket at address (bytes): the device's doorbell. A ring is a\n"
             "hint (the device also polls), so a failed send is not reported; the new value.");

static PyObject *change_ring(PyObject *self, PyObject *args) {
  Py_buffer image, address;
  Py_ssize_t offset;
  unsigned char set, clear, toggle, payload, new;
  int fd;
  struct sockaddr_un to;
  socklen_t length;
  (void)self;
  if (!PyArg_ParseTuple(args, "w*nbbbiy*b", &image, &offset, &set, &clear, &toggle, &fd,
                        &address, &payload))
    return NULL;
  if (offset < 0 || offset >= image.len) {
    PyErr_SetString(PyExc_IndexError, "offset outside the image");
    goto fail;
  }
  if (address.len <= 0 || (size_t)address.len >= sizeof(to.sun_path)) {
    PyErr_SetString(PyExc_ValueError, "not a socket path");
    goto fail;
  }
  memset(&to, 0, sizeof(to));
  to.sun_family = AF_UNIX;
  memcpy(to.sun_path, address.buf, (size_t)address.len);
  length = (socklen_t)(offsetof(struct sockaddr_un, sun_path) + (size_t)address.len + 1);
  new = change_byte((unsigned char *)image.buf + offset, set, clear, toggle);
  PyBuffer_Release(&image);
  PyBuffer_Release(&address);
  /* Not blocking (the socket is), so the interpreter lock stays: releasing and taking it
   * back cost more than the call. Nobody listening, a full queue: the device polls. */
  (void)sendto(fd, &payload, 1, MSG_DONTWAIT, (struct sockaddr *)&to, length);
  return PyLong_FromLong(new);
fail:
  PyBuffer_Release(&image);
  PyBuffer_Release(&address);
  return NULL;
}

PyDoc_STRVAR(wait_ring_doc,
             "wait_ring(fd, timeout, wake=-1) -> int\n\n"
             "Wait up to timeout seconds for the socket fd to be readable, then take every\n"
             "datagram queued on it without waiting: -1 when none came in time, 0 when\n"
             "another thread took it first, else the last one's first byte. wake: a pipe's\n"
             "non-blocking read end also watched (a thread's own wake-up); when it is\n"
             "readable it is emptied, and -2 returned unless a ring came too. timeout 0\n"
             "without wake: the rings queued now, without waiting (-1: none).");

static PyObject *wait_ring(PyObject *self, PyObject *args) {
  int fd, wake = -1, ready, taken, error, i, woken = 0;
  double timeout, whole;
  struct timespec span;
  struct pollfd watched[2];
  nfds_t count = 1;
  unsigned char bytes[RINGS_AT_ONCE], drained[64];
  struct iovec parts[RINGS_AT_ONCE];
  struct mmsghdr rings[RINGS_AT_ONCE];
  (void)self;
  if (!PyArg_ParseTuple(args, "id|i", &fd, &timeout, &wake)) return NULL;
  /* ppoll, not poll: the time-out to the nanosecond, as select's was */
  if (!(timeout > 0)) timeout = 0;
  if (timeout > 86400.0) timeout = 86400.0;
  span.tv_nsec = (long)(modf(timeout, &whole) * 1e9);
  span.tv_sec = (time_t)whole;
  watched[0].fd = fd;
  watched[0].events = POLLIN;
  watched[0].revents = 0;
  if (wake >= 0) {
    /* [ours] the CiA 309 gateway's reader thread: the ring and its own wake-up pipe in one
     * call, not HostBell.wait's select, recvfrom, select and os.read (issue 22) */
    watched[1].fd = wake;
    watched[1].events = POLLIN;
    watched[1].revents = 0;
    count = 2;
  }
  if (timeout == 0 && count == 1) {
    /* no wait: the rings taken at once, without asking ppoll first (an event loop's
     * selector said the socket is readable: the 309-3 server's, once per answer) */
    ready = 1;
    watched[0].revents = POLLIN;
    error = 0;
  } else if (timeout == 0) {
    ready = ppoll(watched, count, &span, NULL);
    error = errno;
  } else {
    Py_BEGIN_ALLOW_THREADS
    ready = ppoll(watched, count, &span, NULL);
    error = errno;
    Py_END_ALLOW_THREADS
  }
  if (ready < 0) {
    if (error != EINTR) {
      errno = error;
      return PyErr_SetFromErrno(PyExc_OSError);
    }
    if (PyErr_CheckSignals() < 0) return NULL;
    return PyLong_FromLong(-1); /* a signal: the caller looks at the flags and waits again */
  }
  if (ready == 0) return PyLong_FromLong(-1);
  if (count == 2 && watched[1].revents) {
    /* every byte written so far: the writer does not block on a full pipe (it is woken
     * already), so emptying it loses no wake-up */
    while (read(wake, drained, sizeof(drained)) == (ssize_t)sizeof(drained)) {
    }
    woken = 1;
  }
  if (!watched[0].revents) return PyLong_FromLong(woken ? -2 : -1);
  memset(rings, 0, sizeof(rings));
  for (i = 0; i < RINGS_AT_ONCE; i++) {
    parts[i].iov_base = &bytes[i];
    parts[i].iov_len = 1;
    rings[i].msg_hdr.msg_iov = &parts[i];
    rings[i].msg_hdr.msg_iovlen = 1;
  }
  taken = recvmmsg(fd, rings, RINGS_AT_ONCE, MSG_DONTWAIT, NULL);
  /* another thread of this process took it; none at all, when nothing was asked first */
  if (taken <= 0) return PyLong_FromLong(timeout == 0 && count == 1 ? -1 : 0);
  return PyLong_FromLong(rings[taken - 1].msg_len > 0 ? bytes[taken - 1] : 0);
}

/* --- the host's mailbox transaction ------------------------------------------------------
 *
 * [ours] ``put_request`` and ``take_answer`` are a Python host's DevPutMessage and
 * DevGetMessage inside the board's transaction lock (host_api/driver.py ``put_inside`` and
 * ``get_inside``) in one call each when nothing has to wait: the message copied, the
 * ledger kept (host_api/locks.py ``Transaction.sent`` and ``answered``), DevFlags toggled
 * and the device rung. The 309-3 server's loop makes both on every read, and their Python
 * steps were about 35 us of its CPU per read (issue 22). Each does exactly what the Python
 * path does, in the same order (a request's line reaches the ledger before DEVCOM tells the
 * card; an answer's line goes after HOSTACK gave the mailbox back), on the Transaction's own
 * fields, under its ``_state`` lock, taken without waiting: the Python path stays the one
 * for every other case (a lock busy, the mailbox full or empty, a stale answer awaited, a
 * sequence continued, a ledger full), and answers None or 0 before it changed anything.
 * The ledger's lines are ``dpm.ledger.LINE``, as libcif writes them (libcif/src/chanlock.c).
 */

#define LINE_MAX_BYTES 96 /* host_api.locks.LEDGER_BYTES' longest line */

static struct {
  int ready;
  Py_ssize_t host_flags, dev_flags, dev_mbx, pc_mbx, ledger_max;
  unsigned char devcom, hostack, dev_pending, host_pending, nak, seq_mask, first, cont, last,
      ring;
  PyObject *unanswered, *request_type, *message_type;
  PyObject *s_state, *s_own, *s_stale, *s_length, *s_ledger, *s_prefix, *s_pid, *s_owner,
      *s_fd, *s_acquire, *s_release;
  PyObject *s_field[8]; /* Message's fields in MSG_STRUC's header order, then its data */
} L;

/* Message's fields by their place in MSG_STRUC's header (rx tx ln nr a f b e: ln is the
 * data's length, so its place names the data) */
static const char *const FIELDS[8] = {"rx", "tx", "data", "nr", "a", "f", "b", "e"};

PyDoc_STRVAR(setup_doc,
             "setup(host_flags, dev_flags, dev_mbx, pc_mbx, devcom, hostack, dev_pending,\n"
             "      host_pending, nak, seq_mask, first, cont, last, ring, ledger_max,\n"
             "      unanswered, request_type, message_type)\n\n"
             "The layout's offsets and bits (dpm), the ledger's Request and dpm's Message\n"
             "types, for put_request and take_answer: once, by host_api.driver.");

static PyObject *setup(PyObject *self, PyObject *args) {
  PyObject *unanswered, *request_type, *message_type;
  (void)self;
  if (!PyArg_ParseTuple(args, "nnnnbbbbbbbbbbnOOO", &L.host_flags, &L.dev_flags, &L.dev_mbx,
                        &L.pc_mbx, &L.devcom, &L.hostack, &L.dev_pending, &L.host_pending,
                        &L.nak, &L.seq_mask, &L.first, &L.cont, &L.last, &L.ring,
                        &L.ledger_max, &unanswered, &request_type, &message_type))
    return NULL;
  if (!PyAnySet_Check(unanswered) || !PyType_Check(request_type) ||
      !PyType_IsSubtype((PyTypeObject *)request_type, &PyTuple_Type) ||
      !PyType_Check(message_type)) {
    PyErr_SetString(PyExc_TypeError, "a set, a tuple type and a type");
    return NULL;
  }
  if (!L.ready) {
#define INTERN(field, text)                                   \
  if ((L.field = PyUnicode_InternFromString(text)) == NULL) \
    return NULL;
    INTERN(s_state, "_state") INTERN(s_own, "_own") INTERN(s_stale, "_stale")
    INTERN(s_length, "_length") INTERN(s_ledger, "_ledger") INTERN(s_prefix, "_prefix")
    INTERN(s_pid, "_pid") INTERN(s_owner, "_owner") INTERN(s_fd, "_fd")
    INTERN(s_acquire, "acquire") INTERN(s_release, "release")
#undef INTERN
    for (int i = 0; i < 8; i++)
      if ((L.s_field[i] = PyUnicode_InternFromString(FIELDS[i])) == NULL) return NULL;
  }
  Py_XSETREF(L.unanswered, Py_NewRef(unanswered));
  Py_XSETREF(L.request_type, Py_NewRef(request_type));
  Py_XSETREF(L.message_type, Py_NewRef(message_type));
  L.ready = 1;
  Py_RETURN_NONE;
}

/* The Transaction's ``_state`` lock taken without waiting: the lock (a new reference) or
 * NULL with no error set when busy, NULL with an error on a failure. */
static PyObject *try_state(PyObject *transaction) {
  PyObject *state = PyObject_GetAttr(transaction, L.s_state), *got;
  if (state == NULL) return NULL;
  got = PyObject_CallMethodOneArg(state, L.s_acquire, Py_False);
  if (got == Py_True) {
    Py_DECREF(got);
    return state;
  }
  Py_XDECREF(got);
  Py_DECREF(state);
  return NULL;
}

static int release_state(PyObject *state) {
  PyObject *done = PyObject_CallMethodNoArgs(state, L.s_release);
  Py_DECREF(state);
  if (done == NULL) return -1;
  Py_DECREF(done);
  return 0;
}

/* A list attribute of the Transaction (a new reference), or NULL with an error. */
static PyObject *list_of(PyObject *transaction, PyObject *name) {
  PyObject *list = PyObject_GetAttr(transaction, name);
  if (list != NULL && !PyList_Check(list)) {
    Py_DECREF(list);
    PyErr_SetString(PyExc_TypeError, "the ledger's requests are not a list");
    return NULL;
  }
  return list;
}

static int int_attr(PyObject *object, PyObject *name, long long *value) {
  PyObject *attr = PyObject_GetAttr(object, name);
  if (attr == NULL) return -1;
  *value = PyLong_AsLongLong(attr);
  Py_DECREF(attr);
  return *value == -1 && PyErr_Occurred() ? -1 : 0;
}

static int byte_attr(PyObject *object, int field, unsigned char *value) {
  long long v;
  PyObject *attr = PyObject_GetAttr(object, L.s_field[field]);
  if (attr == NULL) return -1;
  v = PyLong_AsLongLong(attr);
  Py_DECREF(attr);
  if (v == -1 && PyErr_Occurred()) return -1;
  if (v < 0 || v > 255) {
    PyErr_Format(PyExc_ValueError, "msg.%s = %lld is not a byte", FIELDS[field], v);
    return -1;
  }
  *value = (unsigned char)v;
  return 0;
}

static void ring_device(int fd, PyObject *address) {
  struct sockaddr_un to;
  Py_ssize_t n = PyBytes_GET_SIZE(address);
  if (n <= 0 || (size_t)n >= sizeof(to.sun_path)) return; /* a hint: the device polls */
  memset(&to, 0, sizeof(to));
  to.sun_family = AF_UNIX;
  memcpy(to.sun_path, PyBytes_AS_STRING(address), (size_t)n);
  (void)sendto(fd, &L.ring, 1, MSG_DONTWAIT, (struct sockaddr *)&to,
               (socklen_t)(offsetof(struct sockaddr_un, sun_path) + (size_t)n + 1));
}

/* One request of the ledger as dpm.ledger.LINE writes it, at out (LINE_MAX_BYTES free);
 * its length, or -1 with an error set. */
static int format_request(PyObject *request, char *out) {
  long long f[8];
  int i, n;
  if (!PyTuple_Check(request) || PyTuple_GET_SIZE(request) < 8) {
    PyErr_SetString(PyExc_TypeError, "a ledger request is a tuple of its fields");
    return -1;
  }
  for (i = 0; i < 8; i++) {
    f[i] = PyLong_AsLongLong(PyTuple_GET_ITEM(request, i));
    if (f[i] == -1 && PyErr_Occurred()) return -1;
  }
  n = snprintf(out, LINE_MAX_BYTES, "%lld %lld %lld %lld %lld %lld %lld %lld\n", f[0], f[1],
               f[2], f[3], f[4], f[5], f[6], f[7]);
  if (n < 0 || n >= LINE_MAX_BYTES) {
    PyErr_SetString(PyExc_ValueError, "a ledger line too long");
    return -1;
  }
  return n;
}

static PyObject *new_request(long long pid, long long owner, unsigned char nr, unsigned char b,
                             unsigned char rx, unsigned char tx, int multi, long long sent_ms) {
  PyTypeObject *type = (PyTypeObject *)L.request_type;
  PyObject *r = type->tp_alloc(type, 9);
  PyObject *item;
  long long values[8] = {pid, owner, nr, b, rx, tx, multi, sent_ms};
  int i;
  if (r == NULL) return NULL;
  for (i = 0; i < 8; i++) {
    if ((item = PyLong_FromLongLong(values[i])) == NULL) {
      Py_DECREF(r);
      return NULL;
    }
    PyTuple_SET_ITEM(r, i, item);
  }
  PyTuple_SET_ITEM(r, 8, Py_NewRef(Py_False)); /* given_up */
  return r;
}

PyDoc_STRVAR(put_request_doc,
             "put_request(transaction, image, message, raw, fd, address) -> bool\n\n"
             "put_inside's work when nothing waits: raw (message encoded) copied into the\n"
             "device mailbox, the request recorded (Transaction.sent), DEVCOM toggled, the\n"
             "device rung from the socket fd at address. False, with nothing done, when the\n"
             "Python path must do it: the mailbox full, the ledger's lock busy, a sequence\n"
             "continued or the ledger full.");

static PyObject *put_request(PyObject *self, PyObject *args) {
  PyObject *transaction, *message, *address, *state = NULL, *own = NULL, *stale = NULL;
  PyObject *prefix = NULL, *ledger = NULL, *request = NULL, *key, *result = NULL;
  Py_buffer image, raw, map = {0};
  int fd, record, multi, n;
  unsigned char nr, b, rx, tx, e, sequence, *flags;
  long long at, pid, owner;
  struct timespec now;
  char line[LINE_MAX_BYTES * 2];
  Py_ssize_t prefix_len;
  (void)self;
  if (!L.ready) {
    PyErr_SetString(PyExc_RuntimeError, "setup() first");
    return NULL;
  }
  if (!PyArg_ParseTuple(args, "Ow*Oy*iS", &transaction, &image, &message, &raw, &fd, &address))
    return NULL;
  if (L.dev_mbx + raw.len > image.len || L.host_flags >= image.len || L.dev_flags >= image.len) {
    PyErr_SetString(PyExc_IndexError, "the message outside the image");
    goto done;
  }
  flags = (unsigned char *)image.buf;
  if ((__atomic_load_n(flags + L.host_flags, __ATOMIC_ACQUIRE) ^ flags[L.dev_flags]) &
      L.dev_pending) {
    result = Py_NewRef(Py_False); /* the card has not taken the last one: put_inside waits */
    goto done;
  }
  if (byte_attr(message, 3, &nr) || byte_attr(message, 6, &b) || byte_attr(message, 0, &rx) ||
      byte_attr(message, 1, &tx) || byte_attr(message, 7, &e))
    goto done;
  sequence = e & L.seq_mask;
  if (e & L.nak) {
    record = 0;
  } else {
    if ((key = Py_BuildValue("(ii)", rx, b)) == NULL) goto done;
    record = PySet_Contains(L.unanswered, key);
    Py_DECREF(key);
    if (record < 0) goto done;
    record = !record;
  }
  state = try_state(transaction);
  if (state == NULL) {
    if (!PyErr_Occurred()) result = Py_NewRef(Py_False);
    goto done;
  }
  if (record) {
    if ((own = list_of(transaction, L.s_own)) == NULL ||
        (stale = list_of(transaction, L.s_stale)) == NULL)
      goto unlock;
    if ((PyList_GET_SIZE(own) && (sequence == L.cont || sequence == L.last)) ||
        PyList_GET_SIZE(own) + PyList_GET_SIZE(stale) >= L.ledger_max) {
      result = Py_NewRef(Py_False); /* Transaction.sent rewrites the ledger */
      goto unlock;
    }
    if ((prefix = PyObject_GetAttr(transaction, L.s_prefix)) == NULL) goto unlock;
    if (!PyBytes_Check(prefix) || (prefix_len = PyBytes_GET_SIZE(prefix)) >= LINE_MAX_BYTES) {
      PyErr_SetString(PyExc_TypeError, "the ledger prefix is not bytes");
      goto unlock;
    }
    if (int_attr(transaction, L.s_length, &at) || int_attr(transaction, L.s_pid, &pid) ||
        int_attr(transaction, L.s_owner, &owner))
      goto unlock;
    if ((ledger = PyObject_GetAttr(transaction, L.s_ledger)) == NULL ||
        PyObject_GetBuffer(ledger, &map, PyBUF_WRITABLE) < 0)
      goto unlock;
    clock_gettime(CLOCK_MONOTONIC, &now);
    multi = sequence == L.first;
    memcpy(line, PyBytes_AS_STRING(prefix), (size_t)prefix_len);
    n = snprintf(line + prefix_len, LINE_MAX_BYTES, "%d %d %d %d %d %lld\n", nr, b, rx, tx,
                 multi, (long long)now.tv_sec * 1000 + now.tv_nsec / 1000000);
    if (n < 0 || n >= LINE_MAX_BYTES) goto unlock_full;
    n += (int)prefix_len;
    line[n++] = '\0'; /* dpm.ledger.END */
    if (at < 0 || at + n > map.len) {
    unlock_full:
      result = Py_NewRef(Py_False);
      goto unlock;
    }
    request = new_request(pid, owner, nr, b, rx, tx, multi,
                          (long long)now.tv_sec * 1000 + now.tv_nsec / 1000000);
    if (request == NULL || PyList_Append(own, request) < 0) goto unlock;
    {
      PyObject *length = PyLong_FromLongLong(at + n - 1);
      if (length == NULL || PyObject_SetAttr(transaction, L.s_length, length) < 0) {
        Py_XDECREF(length);
        goto unlock;
      }
      Py_DECREF(length);
    }
    /* Transaction._append's order: a host killed meanwhile leaves the old ledger or the
     * whole line, the line after its first byte written before that byte over END */
    memcpy((char *)map.buf + at + 1, line + 1, (size_t)n - 1);
    __atomic_store_n((char *)map.buf + at, line[0], __ATOMIC_RELEASE);
  }
  memcpy((unsigned char *)image.buf + L.dev_mbx, raw.buf, (size_t)raw.len);
  change_byte(flags + L.dev_flags, 0, 0, L.devcom); /* recorded before the card sees it */
  ring_device(fd, address);
  result = Py_NewRef(Py_True);
unlock:
  if (release_state(state) < 0) Py_CLEAR(result);
done:
  if (map.buf != NULL) PyBuffer_Release(&map);
  Py_XDECREF(ledger);
  Py_XDECREF(request);
  Py_XDECREF(prefix);
  Py_XDECREF(own);
  Py_XDECREF(stale);
  PyBuffer_Release(&image);
  PyBuffer_Release(&raw);
  return result;
}

/* Transaction._store with no stale request left: the ledger rewritten from own, or
 * emptied by one byte. 0, or -1 with an error set. */
static int store_own(PyObject *transaction, PyObject *own, Py_buffer *map) {
  long long at;
  Py_ssize_t i, count = PyList_GET_SIZE(own), used = 0;
  char *text;
  PyObject *length;
  long long fd;
  int n;
  if (int_attr(transaction, L.s_length, &at)) return -1;
  if (count == 0) {
    if (at) ((char *)map->buf)[0] = '\0';
    length = PyLong_FromLong(0);
  } else {
    text = PyMem_Malloc((size_t)count * LINE_MAX_BYTES + 1);
    if (text == NULL) {
      PyErr_NoMemory();
      return -1;
    }
    for (i = 0; i < count; i++) {
      n = format_request(PyList_GET_ITEM(own, i), text + used);
      if (n < 0) {
        PyMem_Free(text);
        return -1;
      }
      used += n;
    }
    text[used] = '\0';
    /* one pwrite, as Transaction._store's: made whole or not at all by a host killed */
    if (int_attr(transaction, L.s_fd, &fd) || pwrite((int)fd, text, (size_t)used + 1, 0) < 0) {
      if (!PyErr_Occurred()) PyErr_SetFromErrno(PyExc_OSError);
      PyMem_Free(text);
      return -1;
    }
    PyMem_Free(text);
    length = PyLong_FromSsize_t(used);
  }
  if (length == NULL) return -1;
  n = PyObject_SetAttr(transaction, L.s_length, length);
  Py_DECREF(length);
  return n;
}

/* Message.decode_at's message of the header head and its data: made as its dataclass'
 * __init__ would (Message has slots and no __post_init__), without running that Python
 * function, a frame on every answer. */
static PyObject *new_message(const unsigned char *head, const unsigned char *data) {
  PyTypeObject *type = (PyTypeObject *)L.message_type;
  PyObject *msg = type->tp_alloc(type, 0), *value;
  int i, failed;
  if (msg == NULL) return NULL;
  for (i = 0; i < 8; i++) {
    value = i == 2 ? PyBytes_FromStringAndSize((const char *)data, head[2])
                   : PyLong_FromLong(head[i]);
    if (value == NULL) {
      Py_DECREF(msg);
      return NULL;
    }
    failed = PyObject_SetAttr(msg, L.s_field[i], value);
    Py_DECREF(value);
    if (failed) {
      Py_DECREF(msg);
      return NULL;
    }
  }
  return msg;
}

PyDoc_STRVAR(take_answer_doc,
             "take_answer(transaction, image, size, fd, address, ring) -> Message | None\n\n"
             "get_inside's work when nothing waits: the message in the host mailbox taken,\n"
             "HOSTACK toggled (and the device rung when ring), the request it answers settled\n"
             "(Transaction.answered). None, with nothing done, when the Python path must do\n"
             "it: the mailbox empty, the message longer than size, the ledger's lock busy or\n"
             "an answer to discard awaited.");

static PyObject *take_answer(PyObject *self, PyObject *args) {
  PyObject *transaction, *address, *state = NULL, *own = NULL, *stale = NULL, *ledger = NULL;
  PyObject *msg = NULL, *result = NULL, *request, *rest;
  Py_buffer image, map = {0};
  Py_ssize_t size, i;
  int fd, ring, multi;
  unsigned char *p, head[8];
  (void)self;
  if (!L.ready) {
    PyErr_SetString(PyExc_RuntimeError, "setup() first");
    return NULL;
  }
  if (!PyArg_ParseTuple(args, "Ow*niSp", &transaction, &image, &size, &fd, &address, &ring))
    return NULL;
  if (L.pc_mbx + 8 + 255 > image.len || L.host_flags >= image.len || L.dev_flags >= image.len) {
    PyErr_SetString(PyExc_IndexError, "the mailbox outside the image");
    goto done;
  }
  p = (unsigned char *)image.buf;
  if (!((__atomic_load_n(p + L.host_flags, __ATOMIC_ACQUIRE) ^ p[L.dev_flags]) &
        L.host_pending)) {
    result = Py_NewRef(Py_None);
    goto done;
  }
  /* rx tx ln nr a f b e, then ln bytes, read after the flag that says they are there; the
   * header copied, as the card may write the next message over it once HOSTACK has given
   * the mailbox back */
  memcpy(head, p + L.pc_mbx, sizeof(head));
  if (8 + head[2] > size) {
    result = Py_NewRef(Py_None);
    goto done;
  }
  state = try_state(transaction);
  if (state == NULL) {
    if (!PyErr_Occurred()) result = Py_NewRef(Py_None);
    goto done;
  }
  if ((own = list_of(transaction, L.s_own)) == NULL ||
      (stale = list_of(transaction, L.s_stale)) == NULL)
    goto unlock;
  if (PyList_GET_SIZE(stale)) {
    result = Py_NewRef(Py_None); /* maybe one to discard: get_inside's loop */
    goto unlock;
  }
  if ((msg = new_message(head, p + L.pc_mbx + 8)) == NULL) goto unlock;
  /* copied before the handshake gives the mailbox back */
  change_byte(p + L.dev_flags, 0, 0, L.hostack);
  if (ring) ring_device(fd, address);
  for (i = 0; i < PyList_GET_SIZE(own); i++) {
    /* Request.answered_by, then Request.after */
    long long f[8];
    int k;
    request = PyList_GET_ITEM(own, i);
    if (!PyTuple_Check(request) || PyTuple_GET_SIZE(request) < 9) {
      PyErr_SetString(PyExc_TypeError, "a ledger request is a tuple of its fields");
      goto unlock;
    }
    for (k = 0; k < 8; k++) {
      f[k] = PyLong_AsLongLong(PyTuple_GET_ITEM(request, k));
      if (f[k] == -1 && PyErr_Occurred()) goto unlock;
    }
    multi = (int)f[6];
    if (multi == 2 && (head[7] & L.seq_mask) != L.cont && (head[7] & L.seq_mask) != L.last)
      continue;
    if (f[2] != head[3] || f[3] != head[4] || f[4] != head[1] || f[5] != head[0]) continue;
    if (multi && head[5] == 0 &&
        ((head[7] & L.seq_mask) == L.first || (head[7] & L.seq_mask) == L.cont)) {
      rest = new_request(f[0], f[1], (unsigned char)f[2], (unsigned char)f[3],
                         (unsigned char)f[4], (unsigned char)f[5], 2, f[7]);
      if (rest == NULL) goto unlock;
      /* given_up as it was */
      Py_SETREF(((PyTupleObject *)rest)->ob_item[8], Py_NewRef(PyTuple_GET_ITEM(request, 8)));
      if (PyList_SetItem(own, i, rest) < 0) goto unlock;
    } else if (PyList_SetSlice(own, i, i + 1, NULL) < 0) {
      goto unlock;
    }
    if ((ledger = PyObject_GetAttr(transaction, L.s_ledger)) == NULL ||
        PyObject_GetBuffer(ledger, &map, PyBUF_WRITABLE) < 0 || store_own(transaction, own, &map))
      goto unlock;
    break;
  }
  result = Py_NewRef(msg);
unlock:
  if (release_state(state) < 0) Py_CLEAR(result);
done:
  if (map.buf != NULL) PyBuffer_Release(&map);
  Py_XDECREF(ledger);
  Py_XDECREF(msg);
  Py_XDECREF(own);
  Py_XDECREF(stale);
  PyBuffer_Release(&image);
  return result;
}

static PyMethodDef methods[] = {
    {"change", change, METH_VARARGS, change_doc},
    {"change_ring", change_ring, METH_VARARGS, change_ring_doc},
    {"wait_ring", wait_ring, METH_VARARGS, wait_ring_doc},
    {"setup", setup, METH_VARARGS, setup_doc},
    {"put_request", put_request, METH_VARARGS, put_request_doc},
    {"take_answer", take_answer, METH_VARARGS, take_answer_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "host_api._devflags",
    "DevFlags changed by one atomic read-modify-write on the mapped byte, and the host's "
    "doorbell calls [ours].",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__devflags(void) { return PyModule_Create(&module); }
