/*
 * host_api.cia309._plainline - the 309-3 plain read's line to its request, and an upload's
 * value to its answer line, each in one call.
 *
 * [ours] The server's event loop parses every 309-3 read and formats its answer: in Python
 * that was nine calls per read (the framer's whole_line, the dispatcher's prepare,
 * parse_request, _plain_read with its regular expression and four int calls; format_upload,
 * format_value and the answer's f-string), 1-2 us each on the loop's thread, which runs on
 * cold caches after its sleep (issue 22, docs/benchmarks.md note 3). These two functions
 * accept a subset of what the Python path accepts and give exactly its result there
 * (tests/test_cia309_ascii.py checks both against it with hypothesis); for anything
 * else they return None, and the caller takes the Python path, which stays the general
 * one.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <stdio.h>
#include <string.h>

static PyObject *upload_keywords; /* ("sequence", "net", "node", "index", "subindex", "dtype") */

static int is_digit(char c) { return c >= '0' && c <= '9'; }

static int hex_value(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

/* A decimal number without a leading zero ("0" itself only when zero_alone), of 1 to
 * max_digits digits, at *p; advances *p past it. -1 when the text is no such number (a
 * digit run longer than max_digits is none: the regular expression's {0,n} ends where the
 * run does not, and the separator it needs next is missing). */
static long long decimal(const char **p, const char *end, int max_digits, int zero_alone) {
  const char *s = *p;
  long long value = 0;
  int digits = 0;
  if (s == end || !is_digit(*s)) return -1;
  if (*s == '0') {
    if (!zero_alone) return -1;
    *p = s + 1;
    return 0; /* a digit after it leaves the separator missing: the caller fails */
  }
  while (s < end && is_digit(*s)) {
    if (++digits > max_digits) return -1;
    value = value * 10 + (*s - '0');
    s++;
  }
  *p = s;
  return value;
}

/* "0x" and 1 to max_hex hexadecimal digits, "0", or a decimal number of 1 to max_decimal
 * digits: an index or subindex as _PLAIN_READ reads them (C's octal excluded). */
static long long object_number(const char **p, const char *end, int max_hex, int max_decimal) {
  const char *s = *p;
  if (end - s >= 2 && s[0] == '0' && s[1] == 'x') {
    long long value = 0;
    int digits = 0, digit;
    s += 2;
    while (s < end && (digit = hex_value(*s)) >= 0) {
      if (++digits > max_hex) return -1;
      value = value * 16 + digit;
      s++;
    }
    if (digits == 0) return -1;
    *p = s;
    return value;
  }
  return decimal(p, end, max_decimal, 1);
}

static int take(const char **p, const char *end, const char *text) {
  size_t length = strlen(text);
  if ((size_t)(end - *p) < length || memcmp(*p, text, length) != 0) return 0;
  *p += length;
  return 1;
}

PyDoc_STRVAR(read_line_doc,
             "read_line(upload, types, max_node, data, max_line) -> request | None\n\n"
             "The SDO upload that data makes when it is one whole line (ended by LF or CR LF,\n"
             "at most max_line bytes without it) in the plain form of a read with no white\n"
             "space around it: upload(sequence=, net=, node=, index=, subindex=, dtype=)\n"
             "with dtype types[name] or None. None otherwise, or when a number is out of\n"
             "range (node above max_node) or the type is not in types.");

static PyObject *read_line(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
  const char *s, *end, *type_start = NULL;
  Py_ssize_t size, max_line;
  long long sequence, first, net = -1, node, index, subindex, max_node;
  PyObject *upload, *types, *dtype = Py_None, *values[7], *result;
  (void)module;
  if (nargs != 5 || !PyDict_Check(args[1]) || !PyBytes_Check(args[3])) {
    PyErr_SetString(PyExc_TypeError, "read_line(callable, dict, int, bytes, int)");
    return NULL;
  }
  upload = args[0];
  types = args[1];
  max_node = PyLong_AsLongLong(args[2]);
  max_line = PyLong_AsSsize_t(args[4]);
  if (PyErr_Occurred()) return NULL;
  s = PyBytes_AS_STRING(args[3]);
  size = PyBytes_GET_SIZE(args[3]);
  if (size >= 2 && s[size - 2] == '\r' && s[size - 1] == '\n') {
    size -= 2;
  } else if (size >= 1 && s[size - 1] == '\n') {
    size -= 1;
  } else {
    Py_RETURN_NONE;
  }
  if (size > max_line) Py_RETURN_NONE; /* the framer reports it as overlong */
  end = s + size;
  /* [seq] */
  if (!take(&s, end, "[")) Py_RETURN_NONE;
  sequence = decimal(&s, end, 9, 1);
  if (sequence < 0 || !take(&s, end, "] ")) Py_RETURN_NONE;
  /* [net] node: a second number before the command makes the first the network */
  first = decimal(&s, end, 5, 0);
  if (first < 0 || !take(&s, end, " ")) Py_RETURN_NONE;
  if (s < end && is_digit(*s)) {
    net = first;
    node = decimal(&s, end, 3, 0);
    if (node < 0 || !take(&s, end, " ")) Py_RETURN_NONE;
  } else {
    if (first > 999) Py_RETURN_NONE; /* a node has three digits at most */
    node = first;
  }
  if (!take(&s, end, "read ") && !take(&s, end, "r ")) Py_RETURN_NONE;
  index = object_number(&s, end, 4, 5);
  if (index < 0 || !take(&s, end, " ")) Py_RETURN_NONE;
  subindex = object_number(&s, end, 2, 3);
  if (subindex < 0) Py_RETURN_NONE;
  if (s < end) {
    if (!take(&s, end, " ")) Py_RETURN_NONE;
    type_start = s;
    while (s < end && (is_digit(*s) || (*s >= 'a' && *s <= 'z'))) s++;
    if (s != end || s - type_start < 1 || s - type_start > 3) Py_RETURN_NONE;
  }
  if (node > max_node || index > 0xFFFF || subindex > 0xFF || net > 0xFFFF) Py_RETURN_NONE;
  if (type_start != NULL) {
    PyObject *name = PyUnicode_DecodeASCII(type_start, end - type_start, NULL);
    if (name == NULL) return NULL;
    dtype = PyDict_GetItemWithError(types, name);
    Py_DECREF(name);
    if (dtype == NULL) {
      if (PyErr_Occurred()) return NULL;
      Py_RETURN_NONE;
    }
  }
  values[0] = NULL; /* PY_VECTORCALL_ARGUMENTS_OFFSET's slot */
  values[1] = PyLong_FromLongLong(sequence);
  values[2] = net < 0 ? Py_NewRef(Py_None) : PyLong_FromLongLong(net);
  values[3] = PyLong_FromLongLong(node);
  values[4] = PyLong_FromLongLong(index);
  values[5] = PyLong_FromLongLong(subindex);
  values[6] = Py_NewRef(dtype);
  result = NULL;
  if (values[1] && values[2] && values[3] && values[4] && values[5]) {
    result = PyObject_Vectorcall(upload, values + 1, PY_VECTORCALL_ARGUMENTS_OFFSET,
                                 upload_keywords);
  }
  for (int i = 1; i < 7; i++) Py_XDECREF(values[i]);
  return result;
}

/* The text of an integer upload's value, as datatypes.format_value spells it; the number
 * of characters written, or -1 when the type is none of BOOLEAN, INTEGERn, UNSIGNEDn, HEXn
 * or its size is not the data's. */
static int integer_text(char *out, size_t room, const char *name, Py_ssize_t name_size,
                        const unsigned char *data, Py_ssize_t size, int lely) {
  unsigned long long value = 0;
  int bits = 0;
  char kind = name[0];
  if (name_size == 1 && kind == 'b') {
    if (size != 1) return -1;
    if (lely) return snprintf(out, room, "%d", data[0] ? 1 : 0);
    return snprintf(out, room, "%u", data[0]);
  }
  if (kind != 'i' && kind != 'u' && kind != 'x') return -1;
  for (Py_ssize_t i = 1; i < name_size; i++) {
    if (!is_digit(name[i]) || bits > 64) return -1;
    bits = bits * 10 + (name[i] - '0');
  }
  if (bits < 8 || bits > 64 || bits % 8 != 0) return -1;
  if (kind == 'x' && bits != 8 && bits != 16 && bits != 32 && bits != 64) return -1;
  if (size != bits / 8) return -1; /* the Python path's length mismatch */
  for (Py_ssize_t i = size - 1; i >= 0; i--) value = (value << 8) | data[i];
  if (kind == 'i') {
    long long signed_value;
    if (bits < 64 && ((value >> (bits - 1)) & 1)) value |= ~0ULL << bits;
    memcpy(&signed_value, &value, sizeof signed_value);
    return snprintf(out, room, "%lld", signed_value);
  }
  if (lely) return snprintf(out, room, "0x%0*llx", (int)(2 * size), value);
  if (kind == 'x') return snprintf(out, room, "0x%0*llX", (int)(2 * size), value);
  return snprintf(out, room, "%llu", value);
}

PyDoc_STRVAR(format_upload_doc,
             "format_upload(lely, line_end, sequence, dtype, data) -> str | None\n\n"
             "The answer line to an SDO upload of data as formatters.format_upload gives\n"
             "it: dtype a BOOLEAN, INTEGERn, UNSIGNEDn or HEXn mnemonic whose size is the\n"
             "data's, or None or 'hex' (the bytes in hex). None for every other type or\n"
             "size, and for a sequence outside 0..2**64-1: the Python path formats those.");

static PyObject *format_upload(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
  unsigned long long sequence;
  const unsigned char *data;
  const char *name = NULL, *line_end;
  Py_ssize_t size, name_size = 0, end_size, used;
  int lely, length;
  char head[32], value[32], *text;
  PyObject *result;
  (void)module;
  if (nargs != 5 || !PyUnicode_Check(args[1]) || !PyLong_Check(args[2]) ||
      (args[3] != Py_None && !PyUnicode_Check(args[3])) || !PyBytes_Check(args[4])) {
    PyErr_SetString(PyExc_TypeError, "format_upload(bool, str, int, str | None, bytes)");
    return NULL;
  }
  sequence = PyLong_AsUnsignedLongLong(args[2]);
  if (sequence == (unsigned long long)-1 && PyErr_Occurred()) {
    PyErr_Clear();
    Py_RETURN_NONE;
  }
  lely = PyObject_IsTrue(args[0]);
  if (lely < 0) return NULL;
  line_end = PyUnicode_AsUTF8AndSize(args[1], &end_size);
  if (line_end == NULL) return NULL;
  if (args[3] != Py_None) {
    name = PyUnicode_AsUTF8AndSize(args[3], &name_size);
    if (name == NULL) return NULL;
    if (name_size == 0) Py_RETURN_NONE;
  }
  data = (const unsigned char *)PyBytes_AS_STRING(args[4]);
  size = PyBytes_GET_SIZE(args[4]);
  length = snprintf(head, sizeof head, "[%llu] ", sequence);
  if (name == NULL || (name_size == 3 && memcmp(name, "hex", 3) == 0)) {
    /* HEX: the bytes as two upper-case digits each, one space between */
    if (size > (PY_SSIZE_T_MAX - length - end_size) / 3) return PyErr_NoMemory();
    text = PyMem_Malloc((size_t)(length + 3 * size + end_size + 1));
    if (text == NULL) return PyErr_NoMemory();
    memcpy(text, head, (size_t)length);
    used = length;
    for (Py_ssize_t i = 0; i < size; i++) {
      static const char digits[] = "0123456789ABCDEF";
      if (i) text[used++] = ' ';
      text[used++] = digits[data[i] >> 4];
      text[used++] = digits[data[i] & 15];
    }
    memcpy(text + used, line_end, (size_t)end_size);
    result = PyUnicode_DecodeASCII(text, used + end_size, NULL);
    PyMem_Free(text);
    return result;
  }
  {
    int value_length = integer_text(value, sizeof value, name, name_size, data, size, lely);
    char line[96];
    if (value_length < 0 || end_size > 8) Py_RETURN_NONE;
    memcpy(line, head, (size_t)length);
    memcpy(line + length, value, (size_t)value_length);
    memcpy(line + length + value_length, line_end, (size_t)end_size);
    return PyUnicode_DecodeASCII(line, length + value_length + end_size, NULL);
  }
}

static PyMethodDef methods[] = {
    {"read_line", (PyCFunction)(void (*)(void))read_line, METH_FASTCALL, read_line_doc},
    {"format_upload", (PyCFunction)(void (*)(void))format_upload, METH_FASTCALL,
     format_upload_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "host_api.cia309._plainline",
    "The 309-3 plain read's line to its request and an upload's answer line, each in one "
    "call [ours].",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__plainline(void) {
  if (upload_keywords == NULL) {
    upload_keywords = Py_BuildValue("(ssssss)", "sequence", "net", "node", "index",
                                    "subindex", "dtype");
    if (upload_keywords == NULL) return NULL;
  }
  return PyModule_Create(&module);
}
