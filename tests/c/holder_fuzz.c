/*
 * holder_fuzz.c - libcif's readers of /proc/locks and /proc/PID/cmdline (libcif/src/holder.c)
 * on tables and command lines written to files: the cases a kernel prints, malformed and
 * overlong lines, records across the reader's chunks, then random files. Run under
 * AddressSanitizer and UBSan (tests/test_busy_board.py): any read outside a buffer fails.
 *
 * Usage: holder_fuzz DIR ROUNDS SEED. Prints "ok CASES" when every case gave its answer.
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "holder.h"

#define WHERE "fe:00:1234"
#define BIG 20000

static char path[4096];
static unsigned cases, failures;

static void put(const char *data, size_t size) {
  FILE *file = fopen(path, "wb");
  if (file == NULL || fwrite(data, 1, size, file) != size || fclose(file) != 0) {
    perror(path);
    exit(2);
  }
}

static void expect_pid(const char *what, const char *table, size_t size, long pid) {
  long got;
  put(table, size);
  got = cifemu_flock_holder(path, WHERE);
  cases++;
  if (got != pid) {
    fprintf(stderr, "holder_fuzz: %s: pid %ld, expected %ld\n", what, got, pid);
    failures++;
  }
}

static void expect_gateway(const char *what, const char *cmdline, size_t size, int gateway) {
  int got;
  put(cmdline, size);
  got = cifemu_gateway_cmdline(path);
  cases++;
  if (got != gateway) {
    fprintf(stderr, "holder_fuzz: %s: %d, expected %d\n", what, got, gateway);
    failures++;
  }
}

#define PID(what, text, pid) expect_pid(what, text, sizeof text - 1, pid)
#define GATEWAY(what, text, gateway) expect_gateway(what, text, sizeof text - 1, gateway)

static void known_tables(void) {
  static char big[BIG];
  char line[200];
  size_t used = 0;
  int n;
  PID("a holder", "1: FLOCK  ADVISORY  WRITE 4242 " WHERE " 0 EOF\n", 4242);
  PID("after other locks",
      "1: POSIX  ADVISORY  WRITE 17 " WHERE " 0 EOF\n"
      "2: FLOCK  ADVISORY  WRITE 18 fe:00:12345 0 EOF\n"
      "3: FLOCK  ADVISORY  WRITE 19 fe:00:123 0 EOF\n"
      "4: FLOCK  ADVISORY  WRITE 20 " WHERE " 0 EOF\n",
      20);
  PID("a waiter only", "1: -> FLOCK  ADVISORY  WRITE 4243 " WHERE " 0 EOF\n", 0);
  PID("tabs", "1:\tFLOCK\tADVISORY\tWRITE\t77\t" WHERE "\t0\tEOF\n", 77);
  PID("no line end", "1: FLOCK  ADVISORY  WRITE 4244 " WHERE " 0 EOF", 4244);
  PID("fields cut", "1: FLOCK ADVISORY WRITE 4245\n", 0);
  PID("pid 0: another namespace", "1: FLOCK  ADVISORY  WRITE 0 " WHERE " 0 EOF\n", 0);
  PID("pid not a number", "1: FLOCK  ADVISORY  WRITE 12a " WHERE " 0 EOF\n", 0);
  PID("pid negative", "1: FLOCK  ADVISORY  WRITE -1 " WHERE " 0 EOF\n", 0);
  PID("pid too long", "1: FLOCK  ADVISORY  WRITE 1234567890 " WHERE " 0 EOF\n", 0);
  PID("a NUL in the line", "1: FLOCK  ADVISORY  WRITE 42\0 " WHERE " 0 EOF\n", 0);
  PID("empty", "", 0);
  PID("blank lines", "\n\n  \n\t\n", 0);
  /* a line longer than the reader's buffer: its first six fields count when they end
     within it, as a line's words do in host_api/holders.py; the next line is read whole */
  n = snprintf(big, sizeof big, "1: FLOCK  ADVISORY  WRITE 54 " WHERE " %0300d\n", 0);
  expect_pid("words past the buffer", big, (size_t)n, 54);
  memset(big, 'x', 300);
  used = 300;
  n = snprintf(line, sizeof line, " 1: FLOCK  ADVISORY  WRITE 55 " WHERE " 0 EOF\n");
  memcpy(big + used, line, (size_t)n);
  used += (size_t)n;
  n = snprintf(line, sizeof line, "2: FLOCK  ADVISORY  WRITE 56 " WHERE " 0 EOF\n");
  memcpy(big + used, line, (size_t)n);
  used += (size_t)n;
  expect_pid("an overlong first word", big, used, 56);
  /* another file whose name starts with the wanted one: the buffer's end must not cut it
     to the wanted name, wherever that end falls */
  for (used = 0; used < 200; used++) {
    memset(big, ' ', used);
    n = snprintf(big + used, sizeof big - used, "1: FLOCK ADVISORY WRITE 59 " WHERE "5 0 EOF\n");
    expect_pid("a longer name cut", big, used + (size_t)n, 0);
  }
  /* this process's own flock is passed over */
  n = snprintf(big, sizeof big,
               "1: FLOCK  ADVISORY  WRITE %ld " WHERE " 0 EOF\n"
               "2: FLOCK  ADVISORY  WRITE 57 " WHERE " 0 EOF\n",
               (long)getpid());
  expect_pid("this process", big, (size_t)n, 57);
  /* the holder's line across the reader's 4096-byte chunks, at every offset near it */
  for (used = 4040; used < 4100; used++) {
    static const char other[] = "9: FLOCK ADVISORY WRITE 8 0:0:1\n";
    size_t at = 0;
    for (; at + sizeof other - 1 <= used; at += sizeof other - 1)
      memcpy(big + at, other, sizeof other - 1);
    memset(big + at, '\n', used - at);
    n = snprintf(big + used, sizeof big - used, "1: FLOCK  ADVISORY  WRITE 58 " WHERE " 0 EOF\n");
    expect_pid("across chunks", big, used + (size_t)n, 58);
  }
  cases++;
  if (cifemu_flock_holder("/nonexistent/locks", WHERE) != 0) failures++;
}

static void known_cmdlines(void) {
  static char big[BIG];
  size_t used;
  GATEWAY("a gateway", "/usr/bin/python3\0-m\0cifemu\0" "309\0serve\0--port\0" "0\0", 1);
  GATEWAY("cifemu 309 serve", "cifemu\0" "309\0serve\0", 1);
  GATEWAY("no line end", "cifemu\0" "309\0serve", 1);
  GATEWAY("an empty word between", "cifemu\0" "309\0\0serve\0", 1);
  GATEWAY("309 exec", "cifemu\0" "309\0exec\0serve\0", 0);
  GATEWAY("the other order", "cifemu\0serve\0" "309\0", 0);
  GATEWAY("one word", "cifemu\0" "309serve\0", 0);
  GATEWAY("a longer word", "cifemu\0" "309\0served\0", 0);
  GATEWAY("empty", "", 0);
  memset(big, 'a', 300);
  memcpy(big + 300, "309\0serve\0", 10);
  expect_gateway("an overlong word ending in 309", big, 310, 0);
  memset(big, 0, sizeof big);
  for (used = 0; used + 4 < BIG - 20; used += 4) memcpy(big + used, "arg", 3);
  memcpy(big + used, "309\0serve\0", 10);
  expect_gateway("after 20 kB of words", big, used + 10, 1);
  cases++;
  if (cifemu_gateway_cmdline("/nonexistent/cmdline") != 0) failures++;
}

/* Random files of pieces a table or command line has, and random bytes: whatever they
   give, they must be read within bounds, and a pid found has at most 9 digits. */
static void random_files(unsigned rounds) {
  static const char *pieces[] = {"FLOCK", " ", "  ", "\t", "\n", "\0", WHERE, "309", "serve",
                                 "1:", "->", "ADVISORY", "WRITE", "4242", "0", "EOF", ":"};
  static char data[BIG];
  unsigned round;
  for (round = 0; round < rounds; round++) {
    size_t size = 0, limit = (size_t)(rand() % BIG);
    long pid;
    while (size < limit) {
      if (rand() % 4 == 0) {
        data[size++] = (char)(rand() % 256);
      } else {
        unsigned which = (unsigned)rand() % (sizeof pieces / sizeof *pieces);
        size_t length = which == 5 ? 1 : strlen(pieces[which]);
        if (size + length > limit) break;
        memcpy(data + size, pieces[which], length);
        size += length;
      }
    }
    put(data, size);
    pid = cifemu_flock_holder(path, WHERE);
    if (pid < 0 || pid > 999999999L) {
      fprintf(stderr, "holder_fuzz: round %u: pid %ld\n", round, pid);
      failures++;
    }
    (void)cifemu_gateway_cmdline(path);
  }
}

int main(int argc, char **argv) {
  if (argc != 4) {
    fprintf(stderr, "usage: holder_fuzz DIR ROUNDS SEED\n");
    return 2;
  }
  snprintf(path, sizeof path, "%s/table", argv[1]);
  srand((unsigned)strtoul(argv[3], NULL, 0));
  known_tables();
  known_cmdlines();
  random_files((unsigned)strtoul(argv[2], NULL, 0));
  if (failures) return 1;
  printf("ok %u\n", cases);
  return 0;
}
