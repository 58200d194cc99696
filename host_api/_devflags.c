/*
 * host_api._devflags - DevFlags changed by one atomic read-modify-write on the mapped byte.
 *
 * [ours] Every host process writes DevFlags (a put toggles DEVCOM, a get HOSTACK, an
 * exchange PDCOM, DevSetHostState NOTREADY ...), Python and C hosts (libcif) alike. A
 * plain read-modify-write from two processes could lose one host's toggle; an flock
 * around it (board<N>.flags.lock until issue 22) cost four system calls per mailbox round
 * trip. A compare-and-swap on the byte itself excludes nobody and costs none; libcif's
 * change_dev_flags does the same (libcif/src/cif_api.c), so the two drivers share a card.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

PyDoc_STRVAR(change_doc,
             "change(image, offset, set_bits, clear_bits, toggle) -> int\n\n"
             "Set, clear, then toggle bits of the byte at offset of the writable buffer\n"
             "image (the board's mmap), atomically across processes; the new value.");

static PyObject *change(PyObject *self, PyObject *args) {
  Py_buffer image;
  Py_ssize_t offset;
  unsigned char set, clear, toggle, old, new;
  unsigned char *p;
  (void)self;
  if (!PyArg_ParseTuple(args, "w*nbbb", &image, &offset, &set, &clear, &toggle)) return NULL;
  if (offset < 0 || offset >= image.len) {
    PyBuffer_Release(&image);
    PyErr_SetString(PyExc_IndexError, "offset outside the image");
    return NULL;
  }
  p = (unsigned char *)image.buf + offset;
  old = __atomic_load_n(p, __ATOMIC_RELAXED);
  do {
    new = (unsigned char)(((old | set) & ~clear) ^ toggle);
    /* seq_cst: what the host wrote before (a message in DevMbx) is seen before the bit */
  } while (!__atomic_compare_exchange_n(p, &old, new, 0, __ATOMIC_SEQ_CST, __ATOMIC_RELAXED));
  PyBuffer_Release(&image);
  return PyLong_FromLong(new);
}

static PyMethodDef methods[] = {
    {"change", change, METH_VARARGS, change_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "host_api._devflags",
    "DevFlags changed by one atomic read-modify-write on the mapped byte [ours].", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__devflags(void) { return PyModule_Create(&module); }
