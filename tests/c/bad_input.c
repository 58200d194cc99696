/*
 * bad_input.c - libcif given a legacy program's mistakes: every one gets its documented
 * code, none crashes. Built plain and with AddressSanitizer/UBSan by
 * tests/test_libcif_c.py, run against a firmware in $CIF_DPM_DIR with board 0 running.
 * argv[1] names a scratch directory for DevDownload's file errors.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "cif_user.h"

static int failures;

#define EXPECT(call, code)                                                          \
  do {                                                                              \
    short got_ = (short)(call);                                                     \
    if (got_ != (code)) {                                                           \
      fprintf(stderr, "bad_input: line %d: %s gave %d, not %d\n", __LINE__, #call,  \
              got_, (int)(code));                                                   \
      failures++;                                                                   \
    }                                                                               \
  } while (0)

static unsigned char buf[8192];

/* Every board function with board number n, all pointers valid: the board's own code.
   DevInitBoard is tried only where it must fail (init_fails). */
static void board_calls(unsigned short n, short code, int init_fails) {
  MSG_STRUC msg;
  COMSTATE state;
  unsigned short a = 0, b = 0;
  unsigned long bytes = 0;
  memset(&msg, 0, sizeof msg);
  msg.rx = 2;
  msg.tx = 16;
  if (init_fails) EXPECT(DevInitBoard(n), n >= MAX_DEV_BOARDS ? DRV_USR_DEV_NUMBER_INVALID : code);
  EXPECT(DevExitBoard(n), code);
  EXPECT(DevPutMessage(n, &msg, 0), code);
  EXPECT(DevGetMessage(n, sizeof msg, &msg, 0), code);
  EXPECT(DevGetMBXState(n, &a, &b), code);
  EXPECT(DevGetMBXData(n, 8, buf, 8, buf + 8), code);
  EXPECT(DevExchangeIO(n, 0, 1, buf, 0, 1, buf, 0), code);
  EXPECT(DevExchangeIOEx(n, 2, 0, 1, buf, 0, 1, buf, 0), code);
  EXPECT(DevExchangeIOErr(n, 0, 1, buf, 0, 1, buf, &state, 0), code);
  EXPECT(DevReadSendData(n, 0, 1, buf), code);
  EXPECT(DevReset(n, WARMSTART, 0), code);
  EXPECT(DevSetHostState(n, HOST_READY, 0), code);
  EXPECT(DevTriggerWatchDog(n, WATCHDOG_STOP, &a), code);
  EXPECT(DevSpecialControl(n, SPECIAL_CONTROL_CLEAR, &a), code);
  EXPECT(DevGetInfo(n, GET_RCS_INFO, 8, buf), code);
  EXPECT(DevGetTaskState(n, 2, 64, buf), code);
  EXPECT(DevGetTaskParameter(n, 2, 64, buf), code);
  EXPECT(DevPutTaskParameter(n, 1, 1, buf), code);
  EXPECT(DevReadWriteDPMRaw(n, PARAMETER_READ, 0, 1, buf), code);
  EXPECT(DevReadWriteDPMData(n, PARAMETER_READ, 0, 1, buf), code);
  EXPECT(DevExtendedData(n, 1, 1, buf), code);
  EXPECT(DevSetOpMode(n, POLLING_MODE, &a), code);
  EXPECT(DevDownload(n, CONFIGURATION_DOWNLOAD, (unsigned char *)"missing.dbm", &bytes),
         DRV_USR_FILE_OPEN_FAILED); /* the file is read before the board is looked at */
}

static void write_file(const char *path, const void *data, size_t size) {
  FILE *f = fopen(path, "wb");
  if (f == NULL) {
    perror(path);
    exit(2);
  }
  fwrite(data, 1, size, f);
  fclose(f);
}

static void download_errors(const char *scratch) {
  char path[4096];
  unsigned long bytes = 99;
  static const unsigned char header[44] = {'D', 'B', 'M', 'F', 'I', 'L', 'E', ' ', ' ', 0};
  unsigned char bad[44 + 16];
  EXPECT(DevDownload(0, CONFIGURATION_DOWNLOAD, NULL, &bytes), DRV_USR_FILENAME_INVALID);
  EXPECT(bytes, 0);
  EXPECT(DevDownload(0, CONFIGURATION_DOWNLOAD, (unsigned char *)"", NULL),
         DRV_USR_FILENAME_INVALID);
  EXPECT(DevDownload(0, FIRMWARE_DOWNLOAD, (unsigned char *)"x.dbm", NULL),
         DRV_DEV_FUNCTION_FAILED);
  EXPECT(DevDownload(0, 0, (unsigned char *)"x.dbm", NULL), DRV_USR_MODE_INVALID);
  EXPECT(DevDownload(0, 3, (unsigned char *)"x.dbm", NULL), DRV_USR_MODE_INVALID);
  EXPECT(DevDownload(0, 2, (unsigned char *)"config.txt", NULL), DRV_USR_INVALID_FILETYPE);
  EXPECT(DevDownload(0, 2, (unsigned char *)".dbm", NULL), DRV_USR_INVALID_FILETYPE);
  snprintf(path, sizeof path, "%s/missing.dbm", scratch);
  EXPECT(DevDownload(0, 2, (unsigned char *)path, NULL), DRV_USR_FILE_OPEN_FAILED);
  snprintf(path, sizeof path, "%s/folder.dbm", scratch);
  mkdir(path, 0700);
  EXPECT(DevDownload(0, 2, (unsigned char *)path, NULL), DRV_USR_FILE_OPEN_FAILED);
  snprintf(path, sizeof path, "%s/empty.dbm", scratch);
  write_file(path, "", 0);
  EXPECT(DevDownload(0, 2, (unsigned char *)path, NULL), DRV_USR_FILE_SIZE_ZERO);
  snprintf(path, sizeof path, "%s/text.DBM", scratch);
  write_file(path, "not a database\n", 15);
  EXPECT(DevDownload(0, 2, (unsigned char *)path, NULL), DRV_USR_INVALID_FILETYPE);
  snprintf(path, sizeof path, "%s/short.dbm", scratch);
  write_file(path, header, 20);
  EXPECT(DevDownload(0, 2, (unsigned char *)path, NULL), DRV_USR_INVALID_FILETYPE);
  /* a header that promises 16 data bytes, followed by 16 bytes without a GLOBAL record */
  memset(bad, 0xFF, sizeof bad);
  memcpy(bad, header, sizeof header);
  bad[38] = 16;
  bad[39] = 0;
  bad[40] = 44;
  bad[41] = bad[42] = bad[43] = 0;
  snprintf(path, sizeof path, "%s/broken.dbm", scratch);
  write_file(path, bad, sizeof bad);
  EXPECT(DevDownload(0, 2, (unsigned char *)path, NULL), DRV_USR_INVALID_FILETYPE);
  write_file(path, bad, sizeof bad - 1); /* shorter than its header says */
  EXPECT(DevDownload(0, 2, (unsigned char *)path, NULL), DRV_USR_INVALID_FILETYPE);
}

int main(int argc, char **argv) {
  BOARD_INFO info;
  BOARD_INFOEX infoex;
  MSG_STRUC msg;
  COMSTATE state;
  unsigned short a = 0, b = 0;
  unsigned i;

  if (argc != 2) {
    fprintf(stderr, "usage: bad_input SCRATCH_DIR\n");
    return 2;
  }
  memset(&msg, 0, sizeof msg);

  /* before DevOpenDriver */
  EXPECT(hDevDrv, -1);
  EXPECT(DevCloseDriver(), DRV_USR_NOT_INITIALIZED);
  EXPECT(DevGetBoardInfo(&info), DRV_USR_NOT_INITIALIZED);
  EXPECT(DevGetBoardInfo(NULL), DRV_USR_NOT_INITIALIZED);
  EXPECT(DevGetBoardInfoEx(&infoex), DRV_USR_NOT_INITIALIZED);
  EXPECT(DevGetBoardInfoEx(NULL), DRV_USR_NOT_INITIALIZED);
  EXPECT(DevGetMessage(0, 0, &msg, 0), DRV_USR_SIZE_INVALID);
  board_calls(0, DRV_USR_NOT_INITIALIZED, 1);
  board_calls(4, DRV_USR_DEV_NUMBER_INVALID, 1);

  EXPECT(DevOpenDriver(), DRV_NO_ERROR);
  if (hDevDrv < 0) {
    fprintf(stderr, "bad_input: hDevDrv is %d while the driver is open\n", hDevDrv);
    failures++;
  }
  EXPECT(DevGetBoardInfo(NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevGetBoardInfoEx(NULL), DRV_USR_BUF_PTR_NULL);
  board_calls(0, DRV_USR_NOT_INITIALIZED, 0);
  for (i = MAX_DEV_BOARDS; i <= 0xFFFF; i += 0x1111)
    board_calls((unsigned short)i, DRV_USR_DEV_NUMBER_INVALID, 1);
  EXPECT(DevInitBoard(1), DRV_USR_DEV_NUMBER_INVALID); /* no image for board 1 */
  EXPECT(DevInitBoard(0), DRV_NO_ERROR);
  EXPECT(DevGetBoardInfoEx(&infoex), DRV_NO_ERROR);
  if (memcmp(infoex.tBoard[0].tDeviceInfo.abDevIdentifier, "CIF", 3) != 0 ||
      infoex.tBoard[0].tDriverInfo.ulOpenCnt != 1) {
    fprintf(stderr, "bad_input: BOARD_INFOEX lacks board 0's areas\n");
    failures++;
  }

  /* null pointers */
  EXPECT(DevPutMessage(0, NULL, 0), DRV_USR_MSG_BUF_NULL_PTR);
  EXPECT(DevGetMessage(0, 288, NULL, 0), DRV_USR_MSG_BUF_NULL_PTR);
  EXPECT(DevGetMBXState(0, NULL, &b), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevGetMBXState(0, &a, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevGetMBXData(0, 8, NULL, 8, buf), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevExchangeIO(0, 0, 4, NULL, 0, 0, NULL, 0), DRV_USR_SENDBUF_PTR_NULL);
  EXPECT(DevExchangeIO(0, 0, 0, NULL, 0, 4, NULL, 0), DRV_USR_RECVBUF_PTR_NULL);
  EXPECT(DevExchangeIOEx(0, 2, 0, 4, NULL, 0, 0, NULL, 0), DRV_USR_SENDBUF_PTR_NULL);
  EXPECT(DevExchangeIOErr(0, 0, 0, NULL, 0, 0, NULL, NULL, 0), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevReadSendData(0, 0, 4, NULL), DRV_DEV_NO_COM_FLAG); /* COM is checked first */
  EXPECT(DevTriggerWatchDog(0, WATCHDOG_STOP, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevSpecialControl(0, SPECIAL_CONTROL_CLEAR, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevGetInfo(0, GET_RCS_INFO, 8, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevGetTaskState(0, 2, 64, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevGetTaskParameter(0, 2, 64, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevPutTaskParameter(0, 2, 3, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevReadWriteDPMRaw(0, PARAMETER_WRITE, 0, 4, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevReadWriteDPMData(0, PARAMETER_READ, 0, 4, NULL), DRV_USR_BUF_PTR_NULL);
  EXPECT(DevSetOpMode(0, INTERRUPT_MODE, NULL), DRV_NO_ERROR);

  /* sizes 0 and too large, offsets past the area */
  EXPECT(DevGetMessage(0, 0, &msg, 0), DRV_USR_SIZE_INVALID);
  EXPECT(DevGetMessage(0, 289, &msg, 0), DRV_USR_SIZE_INVALID);
  EXPECT(DevGetMessage(0, 0xFFFF, &msg, 0), DRV_USR_SIZE_INVALID);
  EXPECT(DevGetMBXData(0, 0, buf, 8, buf), DRV_USR_SIZE_ZERO);
  EXPECT(DevGetMBXData(0, 289, buf, 8, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevGetMBXData(0, 288, buf, 288, buf + 288), DRV_NO_ERROR);
  EXPECT(DevExchangeIO(0, 3584, 1, buf, 0, 0, buf, 0), DRV_USR_SENDSIZE_TOO_LONG);
  EXPECT(DevExchangeIO(0, 0xFFFF, 0xFFFF, buf, 0, 0, buf, 0), DRV_USR_SENDSIZE_TOO_LONG);
  EXPECT(DevExchangeIO(0, 0, 0, buf, 1, 3584, buf, 0), DRV_USR_RECVSIZE_TOO_LONG);
  EXPECT(DevExchangeIO(0, 0, 0, buf, 0xFFFF, 0xFFFF, buf, 0), DRV_USR_RECVSIZE_TOO_LONG);
  EXPECT(DevExchangeIO(0, 0xFFFF, 0, NULL, 0xFFFF, 0, NULL, 0), DRV_DEV_NO_COM_FLAG);
  EXPECT(DevExchangeIO(0, 0, 3584, buf, 0, 3584, buf + 3584, 0), DRV_DEV_NO_COM_FLAG);
  EXPECT(DevExchangeIOEx(0, 5, 0, 0, buf, 0, 0, buf, 0), DRV_USR_MODE_INVALID);
  EXPECT(DevExchangeIOEx(0, 0xFFFF, 0, 0, buf, 0, 0, buf, 0), DRV_USR_MODE_INVALID);
  EXPECT(DevExchangeIOErr(0, 0xFFFF, 1, buf, 0, 0, buf, &state, 0), DRV_USR_SENDSIZE_TOO_LONG);
  EXPECT(DevReadSendData(0, 3584, 1, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevReadSendData(0, 0xFFFF, 0xFFFF, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevGetInfo(0, GET_IO_SEND_DATA, 3585, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevGetInfo(0, GET_IO_SEND_DATA, 3584, buf), DRV_NO_ERROR);
  EXPECT(DevGetInfo(0, GET_DRIVER_INFO, 0xFFFF, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevGetInfo(0, GET_DRIVER_INFO, 0, buf), DRV_USR_SIZE_ZERO);
  EXPECT(DevGetInfo(0, 0, 1, buf), DRV_USR_INFO_AREA_INVALID);
  EXPECT(DevGetInfo(0, 9, 1, buf), DRV_USR_INFO_AREA_INVALID);
  EXPECT(DevGetInfo(0, 0xFFFF, 1, buf), DRV_USR_INFO_AREA_INVALID);
  EXPECT(DevGetTaskState(0, 2, 0, buf), DRV_USR_SIZE_ZERO);
  EXPECT(DevGetTaskState(0, 2, 0xFFFF, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevGetTaskState(0, 0xFFFF, 64, buf), DRV_USR_NUMBER_INVALID);
  EXPECT(DevPutTaskParameter(0, 2, 65, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevPutTaskParameter(0, 2, 0, buf), DRV_USR_SIZE_ZERO);
  EXPECT(DevReadWriteDPMRaw(0, PARAMETER_READ, 1022, 1, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevReadWriteDPMRaw(0, PARAMETER_READ, 0xFFFF, 0xFFFF, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevReadWriteDPMRaw(0, PARAMETER_READ, 0, 1022, buf), DRV_NO_ERROR);
  EXPECT(DevReadWriteDPMRaw(0, 0, 0, 1, buf), DRV_USR_MODE_INVALID);
  EXPECT(DevReadWriteDPMData(0, PARAMETER_READ, 8191, 2, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevReadWriteDPMData(0, PARAMETER_READ, 0xFFFF, 0xFFFF, buf), DRV_USR_SIZE_TOO_LONG);
  EXPECT(DevReadWriteDPMData(0, PARAMETER_READ, 0, 8192, buf), DRV_NO_ERROR);
  EXPECT(DevReadWriteDPMData(0, 3, 0, 1, buf), DRV_USR_MODE_INVALID);
  EXPECT(DevReset(0, 0, 0), DRV_USR_MODE_INVALID);
  EXPECT(DevReset(0, 0xFFFF, 0), DRV_USR_MODE_INVALID);
  EXPECT(DevSetHostState(0, 2, 0), DRV_USR_MODE_INVALID);
  EXPECT(DevTriggerWatchDog(0, 2, &a), DRV_USR_MODE_INVALID);
  EXPECT(DevSpecialControl(0, 2, &a), DRV_USR_MODE_INVALID);
  EXPECT(DevSetOpMode(0, 2, &a), DRV_USR_MODE_INVALID);
  EXPECT(DevExtendedData(0, 1, 1, NULL), DRV_USR_MODE_INVALID);
  download_errors(argv[1]);

  /* a message as long as a message gets: 255 data bytes, answered or refused, never lost */
  msg.rx = 2;
  msg.tx = 16;
  msg.b = 17;
  msg.ln = 255;
  msg.nr = 1;
  EXPECT(DevPutMessage(0, &msg, 1000), DRV_NO_ERROR);
  EXPECT(DevGetMessage(0, 8, &msg, 2000), DRV_NO_ERROR); /* an error answer: 8 bytes */
  EXPECT(msg.f != 0, 1);

  EXPECT(DevExitBoard(0), DRV_NO_ERROR);
  EXPECT(DevExitBoard(0), DRV_USR_NOT_INITIALIZED);
  EXPECT(DevCloseDriver(), DRV_NO_ERROR);
  EXPECT(hDevDrv, -1);
  board_calls(0, DRV_USR_NOT_INITIALIZED, 1);
  EXPECT(DevCloseDriver(), DRV_USR_NOT_INITIALIZED);
  if (failures) fprintf(stderr, "bad_input: %d failures\n", failures);
  else printf("bad_input: every mistake got its code\n");
  return failures ? 1 : 0;
}
