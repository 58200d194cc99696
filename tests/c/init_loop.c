/*
 * init_loop.c - DevInitBoard and DevExitBoard, COUNT times, on a running card
 * (tests/test_lock_table.py). Each DevInitBoard asks /proc/locks whether the firmware
 * holds its lock; beside processes that take and drop many flocks, a held lock can fall
 * between two of the table's pages, and a running card must never be refused as
 * DRV_DEV_NOT_READY for it.
 *
 * Usage: CIF_DPM_DIR=<dir> init_loop COUNT   prints "refused N" and exits 1 when N > 0
 */
#include <stdio.h>
#include <stdlib.h>

#include "cif_user.h"

int main(int argc, char **argv) {
  long count = argc > 1 ? strtol(argv[1], NULL, 10) : 100, i, refused = 0;
  short rc = DevOpenDriver();
  if (rc != DRV_NO_ERROR) {
    fprintf(stderr, "init_loop: DevOpenDriver %d\n", rc);
    return 2;
  }
  for (i = 0; i < count; i++) {
    rc = DevInitBoard(0);
    if (rc != DRV_NO_ERROR) {
      fprintf(stderr, "init_loop: DevInitBoard %d at call %ld\n", rc, i);
      refused++;
      continue;
    }
    DevExitBoard(0);
  }
  DevCloseDriver();
  printf("refused %ld\n", refused);
  return refused > 0;
}
