/*
 * dpm._quicklock - a thread lock whose free acquire reads no clock.
 *
 * [ours] CPython 3.11's threading.Lock computes a deadline from the monotonic clock on
 * every acquire, also a free one and one that does not wait (PyThread_acquire_lock_timed
 * with sem_clockwait). Inside User-Mode Linux, which has no vDSO, each clock reading is a
 * system call, a round trip through the host's ptrace of about 30 us, and a 309-3 read
 * takes the driver's and the ledger's locks seven times on the server's thread (issue 22).
 * It lives in dpm, the one layer that both the firmware and the hosts import.
 * This lock is the same binary semaphore: a free acquire is one sem_trywait, which never
 * enters the kernel; only an acquire that must wait with a time-out reads the clock.
 * Semantics as threading.Lock's: any thread may release it; release of a free lock raises
 * RuntimeError.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <errno.h>
#include <math.h>
#include <semaphore.h>
#include <time.h>

typedef struct {
  PyObject_HEAD
  sem_t sem;
} QuickLock;

static int quicklock_init(PyObject *op, PyObject *args, PyObject *kwds) {
  QuickLock *self = (QuickLock *)op;
  static char *kwlist[] = {NULL};
  if (!PyArg_ParseTupleAndKeywords(args, kwds, ":Lock", kwlist)) return -1;
  if (sem_init(&self->sem, 0, 1) != 0) {
    PyErr_SetFromErrno(PyExc_OSError);
    return -1;
  }
  return 0;
}

static void quicklock_dealloc(PyObject *op) {
  QuickLock *self = (QuickLock *)op;
  sem_destroy(&self->sem);
  Py_TYPE(op)->tp_free(op);
}

/* Wait for the semaphore without the interpreter lock: until taken (1), the deadline
 * passed (0), or a signal handler raised (-1). */
static int wait_for(QuickLock *self, double timeout) {
  struct timespec deadline;
  int status, error;
  if (timeout >= 0) {
    double whole;
    double part = modf(timeout, &whole);
    clock_gettime(CLOCK_MONOTONIC, &deadline);
    deadline.tv_sec += (time_t)whole;
    deadline.tv_nsec += (long)(part * 1e9);
    if (deadline.tv_nsec >= 1000000000L) {
      deadline.tv_sec += 1;
      deadline.tv_nsec -= 1000000000L;
    }
  }
  for (;;) {
    Py_BEGIN_ALLOW_THREADS
    status = timeout < 0 ? sem_wait(&self->sem)
                         : sem_clockwait(&self->sem, CLOCK_MONOTONIC, &deadline);
    error = errno;
    Py_END_ALLOW_THREADS
    if (status == 0) return 1;
    if (error == ETIMEDOUT) return 0;
    if (error != EINTR) {
      errno = error;
      PyErr_SetFromErrno(PyExc_OSError);
      return -1;
    }
    if (PyErr_CheckSignals() < 0) return -1;
  }
}

static PyObject *quicklock_acquire(PyObject *op, PyObject *args, PyObject *kwds) {
  QuickLock *self = (QuickLock *)op;
  static char *kwlist[] = {"blocking", "timeout", NULL};
  int blocking = 1, taken;
  double timeout = -1;
  if (!PyArg_ParseTupleAndKeywords(args, kwds, "|pd:acquire", kwlist, &blocking, &timeout))
    return NULL;
  if (!blocking && timeout != -1) {
    PyErr_SetString(PyExc_ValueError, "can't specify a timeout for a non-blocking call");
    return NULL;
  }
  if (timeout < 0 && timeout != -1) {
    PyErr_SetString(PyExc_ValueError, "timeout value must be a non-negative number");
    return NULL;
  }
  if (sem_trywait(&self->sem) == 0) Py_RETURN_TRUE;
  if (!blocking || timeout == 0) Py_RETURN_FALSE;
  taken = wait_for(self, timeout);
  if (taken < 0) return NULL;
  return PyBool_FromLong(taken);
}

static PyObject *quicklock_release(PyObject *op, PyObject *Py_UNUSED(ignored)) {
  QuickLock *self = (QuickLock *)op;
  int value = 0;
  sem_getvalue(&self->sem, &value);
  if (value > 0) {
    PyErr_SetString(PyExc_RuntimeError, "release unlocked lock");
    return NULL;
  }
  sem_post(&self->sem);
  Py_RETURN_NONE;
}

static PyObject *quicklock_exit(PyObject *op, PyObject *Py_UNUSED(args)) {
  return quicklock_release(op, NULL);
}

static PyObject *quicklock_locked(PyObject *op, PyObject *Py_UNUSED(ignored)) {
  QuickLock *self = (QuickLock *)op;
  int value = 0;
  sem_getvalue(&self->sem, &value);
  return PyBool_FromLong(value <= 0);
}

static PyMethodDef quicklock_methods[] = {
    {"acquire", (PyCFunction)(void (*)(void))quicklock_acquire, METH_VARARGS | METH_KEYWORDS,
     "acquire(blocking=True, timeout=-1) -> bool: as threading.Lock's."},
    {"__enter__", (PyCFunction)(void (*)(void))quicklock_acquire, METH_VARARGS | METH_KEYWORDS,
     "Acquire, waiting as long as it takes."},
    {"release", quicklock_release, METH_NOARGS, "Release; RuntimeError when not held."},
    {"__exit__", quicklock_exit, METH_VARARGS, "Release."},
    {"locked", quicklock_locked, METH_NOARGS, "Whether the lock is held."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject QuickLockType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "dpm._quicklock.Lock",
    .tp_basicsize = sizeof(QuickLock),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = PyDoc_STR("A thread lock whose free acquire reads no clock (threading.Lock's "
                        "semantics otherwise)."),
    .tp_new = PyType_GenericNew,
    .tp_init = quicklock_init,
    .tp_dealloc = quicklock_dealloc,
    .tp_methods = quicklock_methods,
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "dpm._quicklock",
    PyDoc_STR("A thread lock whose free acquire reads no clock (issue 22)."), -1, NULL,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__quicklock(void) {
  PyObject *m;
  if (PyType_Ready(&QuickLockType) < 0) return NULL;
  m = PyModule_Create(&module);
  if (m == NULL) return NULL;
  Py_INCREF(&QuickLockType);
  if (PyModule_AddObject(m, "Lock", (PyObject *)&QuickLockType) < 0) {
    Py_DECREF(&QuickLockType);
    Py_DECREF(m);
    return NULL;
  }
  return m;
}
