/*
 * cross_host.c - a C host's raw DevPutMessage/DevGetMessage pairs on a card another host
 * (a Python one) uses at the same time: every answer this host reads must be its own.
 *
 * Usage: CIF_DPM_DIR=<dir> cross_host COUNT ADDRESS. Each request is a COM_Shared_Memory
 * read at data_adr ADDRESS, which the answer's telegram header echoes: an answer with
 * another address, number or command is the other host's, and fails the run.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "cif_user.h"
#include "com_user.h"
#include "rcs_user.h"

int main(int argc, char **argv) {
  RCS_MESSAGETELEGRAM_10 msg, answer;
  unsigned count, address, i;
  short rc;
  if (argc != 3) {
    fprintf(stderr, "usage: cross_host COUNT ADDRESS\n");
    return 2;
  }
  count = (unsigned)strtoul(argv[1], NULL, 0);
  address = (unsigned)strtoul(argv[2], NULL, 0);
  if ((rc = DevOpenDriver()) != DRV_NO_ERROR || (rc = DevInitBoard(0)) != DRV_NO_ERROR) {
    fprintf(stderr, "cross_host: open: %d\n", rc);
    return 1;
  }
  for (i = 0; i < count; i++) {
    memset(&msg, 0, sizeof msg);
    msg.rx = COM_TASK_PLC;
    msg.tx = COM_TASK_USER;
    msg.ln = RCS_TELEGRAMHEADER_LEN;
    msg.nr = (unsigned char)(i % 255 + 1);
    msg.b = COM_Shared_Memory;
    msg.data_area = COM_SHM_AREA_RECEIVE;
    msg.data_adr = (unsigned short)address;
    msg.data_cnt = 2;
    msg.data_type = TASK_TDT_UINT8;
    msg.function = TASK_TFC_READ;
    rc = DevPutMessage(0, (MSG_STRUC *)&msg, 5000L);
    if (rc != DRV_NO_ERROR) {
      fprintf(stderr, "cross_host: request %u: DevPutMessage %d\n", i, rc);
      return 1;
    }
    rc = DevGetMessage(0, sizeof answer, (MSG_STRUC *)&answer, 5000L);
    if (rc != DRV_NO_ERROR) {
      fprintf(stderr, "cross_host: request %u: DevGetMessage %d\n", i, rc);
      return 1;
    }
    if (answer.nr != msg.nr || answer.a != COM_Shared_Memory || answer.data_adr != address ||
        answer.f != 0) {
      fprintf(stderr, "cross_host: request %u got another host's answer: nr %u a %u adr %u\n",
              i, answer.nr, answer.a, answer.data_adr);
      return 1;
    }
  }
  DevExitBoard(0);
  DevCloseDriver();
  printf("cross_host: %u answers, all this host's own\n", count);
  return 0;
}
