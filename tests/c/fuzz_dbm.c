/*
 * fuzz_dbm.c - dbm_embd.h on mutated DBM files: whatever the bytes, a code and never a
 * read outside the buffer. Built with AddressSanitizer and UBSan by tests/test_libcif_dbm.py.
 *
 * Usage: fuzz_dbm FILE ROUNDS SEED. Each round copies FILE into a buffer of exactly its
 * size, flips, overwrites or cuts bytes, fixes the checksum w0 in half the rounds (so the
 * mutant gets past dbm_init and into the tables), then asks for every handle and data set.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dbm_embd.h"

static unsigned long long state;

static unsigned next(void) { /* xorshift64 */
  state ^= state << 13;
  state ^= state >> 7;
  state ^= state << 17;
  return (unsigned)(state >> 16);
}

static void fix_checksum(unsigned char *buf, size_t size) {
  size_t start = size > 10 && memcmp(buf, "DBMFILE  ", 10) == 0 ? 44 : 0, i;
  unsigned sum = 0;
  if (size < start + 2) return;
  for (i = start + 2; i + 1 < size; i += 2) sum += buf[i] | (unsigned)buf[i + 1] << 8;
  buf[start] = (unsigned char)sum;
  buf[start + 1] = (unsigned char)(sum >> 8);
}

static const char *NAMES[] = {"GLOBAL", "BUS_CAN", "NODES", "BUS_CAN_EXT", "PLC_PARAM",
                              "PROJEKT", "DESCRIPT", "", "NODES_AND_A_VERY_LONG_NAME"};

int main(int argc, char **argv) {
  unsigned char *seed, *buf, out[65535];
  unsigned long rounds, round;
  unsigned short count, length;
  size_t size, cut;
  unsigned handle, set, n, k;
  long ok = 0;
  FILE *f;
  if (argc != 4) return 2;
  f = fopen(argv[1], "rb");
  if (f == NULL) return 2;
  seed = malloc(70000);
  size = fread(seed, 1, 70000, f);
  fclose(f);
  rounds = strtoul(argv[2], NULL, 0);
  state = strtoull(argv[3], NULL, 0) | 1;
  for (round = 0; round < rounds; round++) {
    cut = next() % 8 == 0 ? next() % (size + 1) : size;
    buf = malloc(cut ? cut : 1);
    memcpy(buf, seed, cut);
    for (n = next() % 6; n > 0 && cut > 0; n--) {
      k = next() % (unsigned)cut;
      switch (next() % 3) {
        case 0: buf[k] ^= (unsigned char)(1u << (next() % 8)); break;
        case 1: buf[k] = (unsigned char)next(); break;
        default: buf[k] = next() % 2 ? 0 : 0xFF; break;
      }
    }
    if (next() % 2) fix_checksum(buf, cut);
    if (dbm_init_ex(buf, cut) == DBM_OK) {
      ok++;
      for (k = 0; k < sizeof NAMES / sizeof *NAMES; k++) {
        unsigned char h;
        (void)dbm_get_num((unsigned char *)NAMES[k], &h);
      }
      for (handle = 0; handle < 256; handle++) {
        if (dbm_get_num_of_set((unsigned char)handle, &count) != DBM_OK) count = 3;
        for (set = 0; set <= (unsigned)count + 1 && set < 200; set++) {
          (void)dbm_fast_read((unsigned char)handle, (unsigned short)set, sizeof out, out, &length);
          (void)dbm_fast_read((unsigned char)handle, (unsigned short)set, 3, out, &length);
        }
      }
    }
    free(buf);
  }
  free(seed);
  printf("fuzz_dbm: %lu rounds, %ld readable\n", rounds, ok);
  return 0;
}
