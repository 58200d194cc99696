/*
 * echo.c - a C host program under test: it writes 8 output bytes for a node and waits
 * until the node sends them back on its inputs (a generic I/O module of a cifemu network
 * does), through the driver API of cif_user.h, as a program for the real card does.
 *
 *   echo BOARD OFFSET   prints the inputs in hex; exit status 0 when they came back
 *
 * It finds the card through $CIF_DPM_DIR, which the cif_card fixture sets.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cif_user.h"

int main(int argc, char **argv) {
  unsigned char outputs[8] = {0xde, 0xad, 0xbe, 0xef, 0x01, 0x23, 0x45, 0x67};
  unsigned char inputs[8] = {0};
  unsigned short board, offset;
  time_t deadline = time(NULL) + 10;
  short rc;
  int i;

  if (argc != 3) {
    fprintf(stderr, "usage: echo BOARD OFFSET\n");
    return 2;
  }
  board = (unsigned short)atoi(argv[1]);
  offset = (unsigned short)atoi(argv[2]);
  rc = DevOpenDriver();
  if (rc == DRV_NO_ERROR) rc = DevInitBoard(board);
  if (rc != DRV_NO_ERROR) {
    fprintf(stderr, "echo: cannot open board %u: %d\n", board, rc);
    return 1;
  }
  do {
    rc = DevExchangeIO(board, offset, sizeof outputs, outputs, offset, sizeof inputs, inputs,
                       1000L);
    if (rc != DRV_NO_ERROR) {
      fprintf(stderr, "echo: DevExchangeIO: %d\n", rc);
      break;
    }
  } while (memcmp(inputs, outputs, sizeof inputs) != 0 && time(NULL) < deadline);
  for (i = 0; i < (int)sizeof inputs; i++) printf("%02x", inputs[i]);
  printf("\n");
  DevExitBoard(board);
  DevCloseDriver();
  return rc == DRV_NO_ERROR && memcmp(inputs, outputs, sizeof inputs) == 0 ? 0 : 1;
}
