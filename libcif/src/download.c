/*
 * download.c - DevDownload: a DBM configuration into the card's flash (libcif).
 *
 * The procedure of DBM.md section 4 and host_api/download.py: a first message
 * (RCS_B_LOADFKT, e = RCS_FIRST_MSK, d = MODE_DOWNLOAD_DBM, the 16 root bytes, the
 * 34-byte GLOBAL record), then the whole data area in 240-byte messages (e =
 * RCS_CONT_MSK, the last RCS_LAST_MSK), each answered by the card. The file header
 * is never sent. Return codes as host_api.download's; the time-outs are the real
 * driver's: 10 s for the first message, 1 s for each continuation, 15 s for the last.
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/stat.h>

#include "dpm.h"
#include "driver.h"
#include "rcsdef.h"

#define CIF_API __attribute__((visibility("default")))

static const unsigned char FILE_MAGIC[10] = {'D', 'B', 'M', 'F', 'I', 'L', 'E', ' ', ' ', 0};
#define FILE_HEADER_SIZE 44
#define MAX_FILE_SIZE (FILE_HEADER_SIZE + 0xFFFF)
#define ROOT_BYTES 16
#define GLOBAL_SIZE 34
#define GLOBAL_SLOT 8
#define BLOCK_HEADER 12
#define CHUNK 240
#define USER_TASK 16
#define FIRST_TIMEOUT_MS 10000UL
#define CONT_TIMEOUT_MS 1000UL
#define LAST_TIMEOUT_MS 15000UL
#define LOCK_WAIT_MS 30000UL /* another host's transfer may take this long [ours] */

static unsigned word_at(const unsigned char *p) { return p[0] | (unsigned)p[1] << 8; }

/* GLOBAL's record, found as drivers find it: root slot 8 -> directory -> slot 1. */
static const unsigned char *global_record(const unsigned char *area, size_t size) {
  size_t directory, record, pad, length, start, end;
  if (size < 2 * GLOBAL_SLOT + 2) return NULL;
  directory = word_at(area + 2 * GLOBAL_SLOT);
  if (2 * directory + BLOCK_HEADER + 4 > size) return NULL;
  record = word_at(area + 2 * directory + BLOCK_HEADER + 2);
  if (2 * record + 12 > size) return NULL;
  pad = word_at(area + 2 * record + 8);
  length = word_at(area + 2 * record + 10);
  start = 2 * record + BLOCK_HEADER;
  end = 2 * record + length;
  end = end >= pad ? end - pad : 0;
  if (end > size) end = size;
  if (end < start || end - start != GLOBAL_SIZE) return NULL;
  return area + start;
}

/* The file's bytes, or the driver's file error. */
static short read_file(const char *name, unsigned char **data, size_t *size) {
  const char *base = strrchr(name, '/'), *dot;
  struct stat st;
  FILE *file;
  size_t got;
  base = base != NULL ? base + 1 : name;
  dot = strrchr(base, '.');
  if (dot == NULL || dot == base || strcasecmp(dot, ".dbm") != 0) return DRV_USR_INVALID_FILETYPE;
  if (stat(name, &st) != 0 || S_ISDIR(st.st_mode)) return DRV_USR_FILE_OPEN_FAILED;
  file = fopen(name, "rb");
  if (file == NULL) return DRV_USR_FILE_OPEN_FAILED;
  *data = (unsigned char *)malloc(MAX_FILE_SIZE + 1);
  if (*data == NULL) {
    fclose(file);
    return DRV_USR_FILE_NO_MEMORY;
  }
  got = fread(*data, 1, MAX_FILE_SIZE + 1, file);
  if (ferror(file)) {
    fclose(file);
    return DRV_USR_FILE_READ_FAILED;
  }
  fclose(file);
  *size = got;
  if (got == 0) return DRV_USR_FILE_SIZE_ZERO;
  return DRV_NO_ERROR;
}

typedef struct session {
  unsigned short board;
  unsigned char nr;
} session;

/* One request and its answer; 1000 + f when the card refused. */
static short send_piece(session *s, const unsigned char *data, unsigned ln, unsigned char e,
                        unsigned long timeout) {
  MSG_STRUC msg, answer;
  short rc;
  memset(&msg, 0, sizeof msg);
  s->nr = (unsigned char)(s->nr + 1);
  msg.rx = RCS_TASK;
  msg.tx = USER_TASK;
  msg.ln = (unsigned char)ln;
  msg.nr = s->nr;
  msg.b = RCS_B_LOADFKT;
  msg.e = e;
  memcpy(msg.data, data, ln);
  rc = DevPutMessage(s->board, &msg, timeout);
  if (rc != DRV_NO_ERROR) return rc;
  for (;;) {
    rc = DevGetMessage(s->board, sizeof answer, &answer, timeout);
    if (rc != DRV_NO_ERROR) return rc;
    /* anything else is an indication or a late answer of someone else's */
    if (answer.nr == msg.nr && answer.a == RCS_B_LOADFKT && answer.rx == msg.tx &&
        answer.tx == msg.rx)
      break;
  }
  return answer.f ? (short)(DRV_RCS_ERROR_OFFSET + answer.f) : DRV_NO_ERROR;
}

static short download(unsigned short number, const unsigned char *area, size_t size,
                      unsigned long *pdwBytes) {
  unsigned char first[1 + ROOT_BYTES + GLOBAL_SIZE];
  const unsigned char *record = global_record(area, size);
  session s = {number, 0};
  cifemu_board *b;
  size_t offset;
  short rc;
  if (record == NULL || size < ROOT_BYTES) return DRV_USR_INVALID_FILETYPE;
  b = cifemu_ready_board(number, &rc);
  if (b == NULL) return rc;
  /* the session holds the transaction lock from its first request to its last answer */
  if (!cifemu_txn_enter(&b->txn, LOCK_WAIT_MS)) {
    cifemu_board_leave(b);
    return DRV_CMD_ACTIVE;
  }
  first[0] = MODE_DOWNLOAD_DBM;
  memcpy(first + 1, area, ROOT_BYTES);
  memcpy(first + 1 + ROOT_BYTES, record, GLOBAL_SIZE);
  rc = send_piece(&s, first, sizeof first, RCS_FIRST_MSK, FIRST_TIMEOUT_MS);
  for (offset = 0; rc == DRV_NO_ERROR && offset < size; offset += CHUNK) {
    int last = offset + CHUNK >= size;
    unsigned ln = (unsigned)(last ? size - offset : CHUNK);
    rc = send_piece(&s, area + offset, ln, last ? RCS_LAST_MSK : RCS_CONT_MSK,
                    last ? LAST_TIMEOUT_MS : CONT_TIMEOUT_MS);
    if (rc == DRV_NO_ERROR && pdwBytes != NULL) *pdwBytes = (unsigned long)(offset + ln);
  }
  cifemu_txn_leave(&b->txn);
  cifemu_board_leave(b);
  return rc;
}

/* Mode 2 (CONFIGURATION_DOWNLOAD) stores a DBM; *pdwBytes counts the data-area bytes the
   card acknowledged. [ours] mode 1 (FIRMWARE_DOWNLOAD) gets -25: the emulated card's
   firmware is a program, there is none to replace. */
CIF_API short DevDownload(unsigned short usDevNumber, unsigned short usMode,
                          unsigned char *pszFileName, unsigned long *pdwBytes) {
  unsigned char *raw = NULL;
  size_t size = 0;
  short rc;
  if (pdwBytes != NULL) *pdwBytes = 0;
  if (usMode == FIRMWARE_DOWNLOAD) return DRV_DEV_FUNCTION_FAILED;
  if (usMode != CONFIGURATION_DOWNLOAD) return DRV_USR_MODE_INVALID;
  if (pszFileName == NULL || pszFileName[0] == '\0') return DRV_USR_FILENAME_INVALID;
  rc = read_file((const char *)pszFileName, &raw, &size);
  if (rc == DRV_NO_ERROR) {
    if (size < FILE_HEADER_SIZE || memcmp(raw, FILE_MAGIC, sizeof FILE_MAGIC) != 0 ||
        word_at(raw + 40) + (word_at(raw + 42) << 16) != FILE_HEADER_SIZE ||
        size != FILE_HEADER_SIZE + word_at(raw + 38))
      rc = DRV_USR_INVALID_FILETYPE;
    else
      rc = download(usDevNumber, raw + FILE_HEADER_SIZE, size - FILE_HEADER_SIZE, pdwBytes);
  }
  free(raw);
  return rc;
}
