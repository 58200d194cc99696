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

static PyMethodDef methods[] = {
    {"change", change, METH_VARARGS, change_doc},
    {"change_ring", change_ring, METH_VARARGS, change_ring_doc},
    {"wait_ring", wait_ring, METH_VARARGS, wait_ring_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "host_api._devflags",
    "DevFlags changed by one atomic read-modify-write on the mapped byte, and the host's "
    "doorbell calls [ours].",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__devflags(void) { return PyModule_Create(&module); }
