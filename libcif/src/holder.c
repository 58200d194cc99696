/* holder.c - see holder.h. */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include "holder.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/sysmacros.h>
#include <unistd.h>

#define PROC_LOCKS "/proc/locks"
#define RECORD_MAX 128 /* a line of /proc/locks is under 100 bytes, a word we seek 5 */
#define READ_CHUNK 4096
#define READ_MAX (16L << 20) /* no more of a file: a table that long is not the kernel's */
#define LOCKS_FIELDS 6       /* "1: FLOCK  ADVISORY  WRITE 18121 fe:00:10004389 0 EOF" */
#define PID_DIGITS 9         /* pid_max is at most 4194304 */

/* Handles one record (a line, a word) of at most RECORD_MAX bytes; whole is 0 when the
   record was longer and is cut. Nonzero ends the reading. */
typedef int (*record_fn)(void *context, const char *record, size_t length, int whole);

/* Calls fn on each record of the file, records ending in sep (the last one may not);
   returns what fn returned to end it, else 0 (also when the file cannot be read). */
static int each_record(const char *path, char sep, record_fn fn, void *context) {
  char chunk[READ_CHUNK], record[RECORD_MAX];
  size_t used = 0;
  int whole = 1, done = 0;
  long at = 0;
  int fd = open(path, O_RDONLY | O_CLOEXEC);
  if (fd < 0) return 0;
  while (!done && at < READ_MAX) {
    ssize_t got = pread(fd, chunk, sizeof chunk, (off_t)at), i;
    if (got < 0 && errno == EINTR) continue;
    if (got <= 0) break;
    at += (long)got;
    for (i = 0; i < got && !done; i++) {
      if (chunk[i] == sep) {
        done = fn(context, record, used, whole);
        used = 0;
        whole = 1;
      } else if (used < sizeof record) {
        record[used++] = chunk[i];
      } else {
        whole = 0;
      }
    }
  }
  if (!done && (used > 0 || !whole)) done = fn(context, record, used, whole);
  close(fd);
  return done;
}

static int same(const char *text, size_t length, const char *word) {
  return length == strlen(word) && memcmp(text, word, length) == 0;
}

static int blank(char c) { return c == ' ' || (c >= '\t' && c <= '\r'); }

typedef struct flock_wanted {
  const char *where;
  long self, pid;
} flock_wanted;

/* One line of /proc/locks: an flock held (a waiter's line reads "1: -> FLOCK ...") on the
   wanted file by a process the line names (pid 0: one outside this pid namespace). Only
   the first six fields count; in a line cut by the buffer they must end before the cut. */
static int flock_line(void *context, const char *line, size_t length, int whole) {
  flock_wanted *wanted = (flock_wanted *)context;
  const char *field[LOCKS_FIELDS];
  size_t size[LOCKS_FIELDS], i = 0, n = 0;
  long pid = 0;
  while (n < LOCKS_FIELDS) {
    while (i < length && blank(line[i])) i++;
    if (i == length) break;
    field[n] = line + i;
    while (i < length && !blank(line[i])) i++;
    size[n] = (size_t)(line + i - field[n]);
    n++;
  }
  if (n < LOCKS_FIELDS || (!whole && i == length) || !same(field[1], size[1], "FLOCK") ||
      !same(field[5], size[5], wanted->where) || size[4] > PID_DIGITS)
    return 0;
  for (i = 0; i < size[4]; i++) {
    if (field[4][i] < '0' || field[4][i] > '9') return 0;
    pid = pid * 10 + (field[4][i] - '0');
  }
  if (pid == 0 || pid == wanted->self) return 0;
  wanted->pid = pid;
  return 1;
}

long cifemu_flock_holder(const char *table, const char *where) {
  flock_wanted wanted;
  wanted.where = where;
  wanted.self = (long)getpid();
  wanted.pid = 0;
  return each_record(table, '\n', flock_line, &wanted) ? wanted.pid : 0;
}

/* One word of a command line; empty ones are skipped, as host_api/holders.py does. */
static int gateway_word(void *context, const char *word, size_t length, int whole) {
  int *after_309 = (int *)context;
  if (length == 0 && whole) return 0;
  if (*after_309 && whole && same(word, length, "serve")) return 1;
  *after_309 = whole && same(word, length, "309");
  return 0;
}

int cifemu_gateway_cmdline(const char *cmdline) {
  int after_309 = 0;
  return each_record(cmdline, '\0', gateway_word, &after_309);
}

int cifemu_held_for_life(int fd) {
  struct stat st;
  char where[64], cmdline[40];
  long pid;
  if (fstat(fd, &st) != 0) return 0;
  snprintf(where, sizeof where, "%02x:%02x:%llu", major(st.st_dev), minor(st.st_dev),
           (unsigned long long)st.st_ino);
  pid = cifemu_flock_holder(PROC_LOCKS, where);
  if (pid == 0) return 0;
  snprintf(cmdline, sizeof cmdline, "/proc/%ld/cmdline", pid);
  return cifemu_gateway_cmdline(cmdline);
}
