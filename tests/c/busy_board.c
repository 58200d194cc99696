/*
 * busy_board.c - a C host on a board whose transaction lock another process holds
 * (tests/test_busy_board.py): the mailbox calls and DevDownload, each with its code and
 * the milliseconds it took.
 *
 * Usage: CIF_DPM_DIR=<dir> busy_board TIMEOUT_MS DBM
 * Prints "put RC MS", "get RC MS" (both with TIMEOUT_MS) and "download RC MS".
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cif_user.h"
#include "com_user.h"
#include "rcs_user.h"

static long long now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (long long)ts.tv_sec * 1000LL + ts.tv_nsec / 1000000L;
}

int main(int argc, char **argv) {
  RCS_MESSAGETELEGRAM_10 msg, answer;
  unsigned long timeout, bytes = 0;
  long long started;
  short rc;
  if (argc != 3) {
    fprintf(stderr, "usage: busy_board TIMEOUT_MS DBM\n");
    return 2;
  }
  timeout = strtoul(argv[1], NULL, 0);
  if ((rc = DevOpenDriver()) != DRV_NO_ERROR || (rc = DevInitBoard(0)) != DRV_NO_ERROR) {
    fprintf(stderr, "busy_board: open: %d\n", rc);
    return 1;
  }
  memset(&msg, 0, sizeof msg);
  msg.rx = COM_TASK_PLC;
  msg.tx = COM_TASK_USER;
  msg.ln = RCS_TELEGRAMHEADER_LEN;
  msg.nr = 1;
  msg.b = COM_Shared_Memory;
  msg.data_area = COM_SHM_AREA_RECEIVE;
  msg.data_cnt = 2;
  msg.data_type = TASK_TDT_UINT8;
  msg.function = TASK_TFC_READ;
  started = now_ms();
  rc = DevPutMessage(0, (MSG_STRUC *)&msg, timeout);
  printf("put %d %lld\n", rc, now_ms() - started);
  started = now_ms();
  rc = DevGetMessage(0, sizeof answer, (MSG_STRUC *)&answer, timeout);
  printf("get %d %lld\n", rc, now_ms() - started);
  started = now_ms();
  rc = DevDownload(0, CONFIGURATION_DOWNLOAD, (unsigned char *)argv[2], &bytes);
  printf("download %d %lld\n", rc, now_ms() - started);
  DevExitBoard(0);
  DevCloseDriver();
  return 0;
}
