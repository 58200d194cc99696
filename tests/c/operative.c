/*
 * operative.c - seed manual chapter 7.2, getting the card operative without SyCon,
 * as a legacy C host does it through libcif, against a firmware with simulated nodes.
 *
 *   1. examine HostFlags directly: READY and RUN mean a SyCon database is loaded;
 *      then delete it with the RCS load function and go on with step 2;
 *   2. write the protocol parameters into the Task2Parameter area;
 *   3. write WARMSTART (INIT, 0x40) into DevFlags and wait for the card;
 *   4. download the network's configuration by messages: the node parameter sets,
 *      then the bus parameters, which start the network;
 * then use the running network: process data, SDO, node diagnostics and NMT.
 * The image is reached "directly" through DevReadWriteDPMData (offsets from the image's
 * start), as a program with the dual-port memory mapped would write it.
 *
 * Usage: CIF_DPM_DIR=<dir> operative [SYCON.dbm]; nodes 1 and 2 echo their outputs as inputs.
 * With a DBM file, the program first puts it into the card's flash with DevDownload and
 * cold-starts the card from it, as SyCon would have left the card: step 1 then deletes it.
 * Exit status 0 when every step did what the seed says, else 1 with the failed step.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cif_user.h"
#include "com_user.h"
#include "rcs_user.h"
#include "rcsdef.h"

#define BOARD 0
#define HOST_FLAGS 0x1FFE
#define DEV_FLAGS 0x1FFF
#define TASK2_PARAMETER 0x1EC0
#define READY_FLAG 0x80
#define RUN_FLAG 0x40
#define INIT_FLAG 0x40 /* DevFlags: warm start request */

#define CHECK(cond, ...)                                         \
  do {                                                           \
    if (!(cond)) {                                               \
      fprintf(stderr, "operative: line %d: ", __LINE__);         \
      fprintf(stderr, __VA_ARGS__);                              \
      fputc('\n', stderr);                                       \
      exit(1);                                                   \
    }                                                            \
  } while (0)

static unsigned char nr;

static double now(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec / 1e9;
}

static void pause_ms(long ms) {
  struct timespec ts = {ms / 1000, (ms % 1000) * 1000000L};
  nanosleep(&ts, NULL);
}

static unsigned char read_byte(unsigned short offset) {
  unsigned char value = 0;
  short rc = DevReadWriteDPMData(BOARD, PARAMETER_READ, offset, 1, &value);
  CHECK(rc == DRV_NO_ERROR, "DevReadWriteDPMData read %#x: %d", offset, rc);
  return value;
}

/* A command and its answer (rx/tx swapped, a == b, nr echoed); returns msg.f. */
static int transact(RCS_MESSAGETELEGRAM_10 *msg, RCS_MESSAGETELEGRAM_10 *answer) {
  short rc;
  msg->nr = ++nr;
  msg->a = msg->f = 0;
  rc = DevPutMessage(BOARD, (MSG_STRUC *)msg, 2000L);
  CHECK(rc == DRV_NO_ERROR, "DevPutMessage b=%d: %d", msg->b, rc);
  do {
    rc = DevGetMessage(BOARD, sizeof *answer, (MSG_STRUC *)answer, 5000L);
    CHECK(rc == DRV_NO_ERROR, "DevGetMessage for b=%d: %d", msg->b, rc);
  } while (answer->nr != msg->nr || answer->a != msg->b);
  CHECK(answer->rx == msg->tx && answer->tx == msg->rx, "answer not addressed back");
  return answer->f;
}

static void new_message(RCS_MESSAGETELEGRAM_10 *msg, unsigned char task, unsigned char command,
                        unsigned char ln) {
  memset(msg, 0, sizeof *msg);
  msg->rx = task;
  msg->tx = COM_TASK_USER;
  msg->b = command;
  msg->ln = ln;
}

/* A COM_Download of one data set in one message (it fits in 240 bytes). */
static void com_download(unsigned char area, const void *data, unsigned short size) {
  RCS_MESSAGE msg;
  RCS_MESSAGETELEGRAM_10 answer;
  COM_DOWNLOAD_REQUEST *request = (COM_DOWNLOAD_REQUEST *)msg.d;
  int f;
  CHECK(size <= COM_MAX_LEN_DATA_UNIT, "data set too long");
  new_message((RCS_MESSAGETELEGRAM_10 *)&msg, COM_TASK_CAN, COM_Download, (unsigned char)(4 + size));
  request->bReq_Adr = 0;
  request->bArea_Code = area;
  request->usAdd_Offset = 0;
  memcpy(request->abData, data, size);
  f = transact((RCS_MESSAGETELEGRAM_10 *)&msg, &answer);
  CHECK(f == 0, "COM_Download area %d: msg.f %d", area, f);
}

/* The node parameter data set of a generic I/O node: heartbeat 500 ms, one RXPDO and one
   TXPDO of 8 bytes at the given I/O offsets (seed 5.2.5.1.1). */
static unsigned short node_data_set(unsigned char *out, unsigned char node, unsigned short offset) {
  COM_ND_PRM_HEADER header;
  COM_SDO_CFG_DATA sdo;
  COM_PDO_DATA pdo[2];
  unsigned short length, list;
  unsigned short io[2];
  unsigned char counts[2] = {1, 1};
  unsigned char *p = out;

  memset(&header, 0, sizeof header);
  header.bNd_Flag = COM_ND_FLAG_ACTIVE | COM_ND_FLAG_HRTBT;
  header.usAddTypeInfo = 0x000F;
  header.usDevProfNum = 401;
  header.usCobIDEmcy = (unsigned short)(0x80 + node);
  header.usCobIDGuard = (unsigned short)(0x700 + node);
  header.usGuardTime = 1000; /* heartbeat consumer time, ms */
  p += sizeof header;

  list = sizeof list + sizeof sdo;
  memcpy(p, &list, sizeof list);
  p += sizeof list;
  memset(&sdo, 0, sizeof sdo);
  sdo.usIndex = 0x1017; /* the node's heartbeat producer time */
  sdo.bSubindex = 0;
  sdo.bLength = 2;
  sdo.abSdoValue[0] = 500 & 0xFF;
  sdo.abSdoValue[1] = 500 >> 8;
  memcpy(p, &sdo, sizeof sdo);
  p += sizeof sdo;

  list = sizeof list + sizeof pdo;
  memcpy(p, &list, sizeof list);
  p += sizeof list;
  memset(pdo, 0, sizeof pdo);
  pdo[0].bTypeOfPdo = 0; /* RXPDO: the master's outputs */
  pdo[0].bLength = 8;
  pdo[0].usPdoCOBId = (unsigned short)(0x200 + node);
  pdo[0].bTransType = 255;
  pdo[1].bTypeOfPdo = 1; /* TXPDO: the master's inputs */
  pdo[1].bLength = 8;
  pdo[1].usPdoCOBId = (unsigned short)(0x180 + node);
  pdo[1].bTransType = 255;
  memcpy(p, pdo, sizeof pdo);
  p += sizeof pdo;

  list = 2 + 2 + sizeof io;
  memcpy(p, &list, sizeof list);
  memcpy(p + 2, counts, 2);
  io[0] = offset; /* input offset */
  io[1] = offset; /* output offset */
  memcpy(p + 4, io, sizeof io);
  p += list;

  length = (unsigned short)(p - out);
  header.usNodeParaLen = length;
  memcpy(out, &header, sizeof header);
  return length;
}

static COM_DIAGNOSTICS diagnostics(void) {
  COM_DIAGNOSTICS diag;
  short rc = DevGetTaskState(BOARD, 2, sizeof diag, &diag);
  CHECK(rc == DRV_NO_ERROR, "DevGetTaskState: %d", rc);
  return diag;
}

static int node_bit(const unsigned char *field, unsigned node) {
  return (field[node / 8] >> (node % 8)) & 1;
}

static int sdo(unsigned char node, unsigned short index, unsigned char subindex,
               unsigned char function, const unsigned char *data, unsigned char count,
               RCS_MESSAGETELEGRAM_10 *answer) {
  RCS_MESSAGETELEGRAM_10 msg;
  new_message(&msg, COM_TASK_CAN, COM_SDO_Up_Download,
              (unsigned char)(RCS_TELEGRAMHEADER_LEN + (function == TASK_TFC_WRITE ? count : 0)));
  msg.device_adr = node;
  msg.data_adr = index;
  msg.data_idx = subindex;
  msg.data_cnt = function == TASK_TFC_WRITE ? count : 0;
  msg.function = function;
  if (function == TASK_TFC_WRITE) memcpy(msg.d, data, count);
  return transact(&msg, answer);
}

/* COM_NMT_Module_Protocol, then wait until the node's Nd_state bit reads `operating`. */
static void nmt(unsigned char command, unsigned char node, int operating) {
  RCS_MESSAGETELEGRAM_10 msg, answer;
  COM_NMT_REQUEST *request = (COM_NMT_REQUEST *)&msg.device_adr;
  double deadline;
  int f;
  new_message(&msg, COM_TASK_CAN, COM_NMT_Module_Protocol, sizeof *request);
  request->bNmtCmd = command;
  request->bNodeID = node;
  f = transact(&msg, &answer);
  CHECK(f == 0, "NMT %#x to node %d: msg.f %d", command, node, f);
  deadline = now() + 5.0;
  while (node_bit(diagnostics().abNd_state, node) != operating) {
    CHECK(now() < deadline, "node %d's Nd_state bit is not %d after NMT %#x", node, operating,
          command);
    pause_ms(5);
  }
}

/* DevDownload of a SyCon-style database, then a cold start: the card runs from it. */
static void download_database(const char *path) {
  unsigned long bytes = 0;
  long size;
  short rc;
  FILE *file = fopen(path, "rb");
  CHECK(file != NULL, "cannot open %s", path);
  fseek(file, 0, SEEK_END);
  size = ftell(file);
  fclose(file);
  rc = DevDownload(BOARD, CONFIGURATION_DOWNLOAD, (unsigned char *)path, &bytes);
  CHECK(rc == DRV_NO_ERROR, "DevDownload: %d", rc);
  CHECK((long)bytes == size - 44, "DevDownload counted %lu bytes of %ld", bytes, size - 44);
  rc = DevReset(BOARD, COLDSTART, 5000L);
  CHECK(rc == DRV_NO_ERROR, "DevReset(COLDSTART): %d", rc);
  printf("step 0: %lu bytes of database downloaded, card cold-started from it\n", bytes);
}

int main(int argc, char **argv) {
  RCS_MESSAGETELEGRAM_10 msg, answer;
  COM_PLC_PARAMETER param;
  COM_ND_DIAGNOSTICS nd;
  COM_DIAGNOSTICS diag;
  BUS_CAN bus;
  unsigned char set[COM_MAX_LEN_DATA_UNIT], out[8], in[8], value[4];
  unsigned short length;
  double deadline;
  unsigned node;
  short rc;
  int f;

  CHECK((rc = DevOpenDriver()) == DRV_NO_ERROR, "DevOpenDriver: %d", rc);
  CHECK((rc = DevInitBoard(BOARD)) == DRV_NO_ERROR, "DevInitBoard: %d", rc);
  if (argc > 1) download_database(argv[1]);

  /* 1. a SyCon database loaded? Then delete it (RCS load function, mode 4, segment 8). */
  if ((read_byte(HOST_FLAGS) & (READY_FLAG | RUN_FLAG)) == (READY_FLAG | RUN_FLAG)) {
    new_message(&msg, RCS_TASK, RCS_B_LOADFKT, 2);
    msg.device_adr = MODE_DEL_FLASH; /* d[0] */
    msg.data_area = 8;               /* d[1]: the database's start segment */
    f = transact(&msg, &answer);
    CHECK(f == 0, "delete database: msg.f %d", f);
    printf("step 1: the card ran from a database: deleted\n");
  } else {
    printf("step 1: no database in the card\n");
  }

  /* 2. the protocol parameters, written into Task2Parameter directly */
  memset(&param, 0, sizeof param);
  param.bMode = CANM_SET_MODE_BUFFERED_HOST_CONTROLLED;
  param.usWatchDogTime = 0;
  rc = DevReadWriteDPMData(BOARD, PARAMETER_WRITE, TASK2_PARAMETER, 3, &param);
  CHECK(rc == DRV_NO_ERROR, "write Task2Parameter: %d", rc);

  /* 3. WARMSTART = 0x40 into DevFlags; the card clears it and comes back READY, not RUN */
  value[0] = INIT_FLAG;
  rc = DevReadWriteDPMData(BOARD, PARAMETER_WRITE, DEV_FLAGS, 1, value);
  CHECK(rc == DRV_NO_ERROR, "write DevFlags: %d", rc);
  deadline = now() + 5.0;
  while ((read_byte(DEV_FLAGS) & INIT_FLAG) || !(read_byte(HOST_FLAGS) & READY_FLAG)) {
    CHECK(now() < deadline, "the card did not finish its warm start");
    pause_ms(1);
  }
  CHECK(!(read_byte(HOST_FLAGS) & RUN_FLAG), "RUN after the warm start: the database is still there");
  printf("step 3: warm start done, HostFlags %#04x\n", read_byte(HOST_FLAGS));

  /* 4. the configuration by messages: nodes 1 and 2, then the bus parameters */
  for (node = 1; node <= 2; node++) {
    length = node_data_set(set, (unsigned char)node, (unsigned short)(8 * (node - 1)));
    com_download((unsigned char)node, set, length);
  }
  memset(&bus, 0, sizeof bus);
  bus.Baud_rate = COM_BAUD_500;
  bus.COB_ID_SYNC = 0x80;
  bus.SYNC_Timer = 10;
  bus.Auto_Clear = ACLR_INACTIVE;
  bus.Intel_Motorola = INTEL;
  com_download(COM_AREA_BUS_PARAMETER, &bus, sizeof bus);
  deadline = now() + 10.0;
  for (;;) {
    diag = diagnostics();
    if (diag.bCAN_State == CAN_STATE_OPERATE && node_bit(diag.abNd_state, 1) &&
        node_bit(diag.abNd_state, 2))
      break;
    CHECK(now() < deadline, "the network did not start: CAN_state %#x, Err_Event %d at %d",
          diag.bCAN_State, diag.tError.bErr_event, diag.tError.bErr_rem_adr);
    pause_ms(5);
  }
  CHECK(node_bit(diag.abNd_cfg, 1) && node_bit(diag.abNd_cfg, 2), "Nd_cfg lacks a node");
  printf("step 4: the network runs, nodes 1 and 2 operational\n");

  /* process data: the nodes echo their outputs into their inputs */
  for (node = 0; node < 8; node++) out[node] = (unsigned char)(0xA0 + node);
  deadline = now() + 5.0;
  for (;;) {
    rc = DevExchangeIO(BOARD, 0, sizeof out, out, 0, sizeof in, in, 1000L);
    CHECK(rc == DRV_NO_ERROR, "DevExchangeIO: %d", rc);
    if (memcmp(in, out, sizeof in) == 0) break;
    CHECK(now() < deadline, "node 1 did not echo its outputs");
  }
  printf("process data: node 1 echoed its outputs\n");

  /* SDO: read the device type, write and read back the heartbeat time */
  f = sdo(1, 0x1000, 0, TASK_TFC_READ, NULL, 0, &answer);
  CHECK(f == 0 && answer.data_cnt == 4, "SDO upload 1000h: msg.f %d, %d bytes", f, answer.data_cnt);
  CHECK(answer.d[0] == 0x91 && answer.d[1] == 0x01, "device type profile is not 401");
  value[0] = 300 & 0xFF;
  value[1] = 300 >> 8;
  f = sdo(1, 0x1017, 0, TASK_TFC_WRITE, value, 2, &answer);
  CHECK(f == 0, "SDO download 1017h: msg.f %d", f);
  f = sdo(1, 0x1017, 0, TASK_TFC_READ, NULL, 0, &answer);
  CHECK(f == 0 && answer.d[0] == (300 & 0xFF) && answer.d[1] == (300 >> 8), "1017h not 300");
  f = sdo(1, 0x6FFF, 9, TASK_TFC_READ, NULL, 0, &answer);
  CHECK(f == 3, "SDO upload of a missing object: msg.f %d, not 3 (abort)", f);
  printf("SDO: device type 401, heartbeat time written and read back, abort reported\n");

  /* node diagnostics */
  new_message(&msg, COM_TASK_CAN, COM_Node_Diag, RCS_TELEGRAMHEADER_LEN);
  msg.device_adr = 2;
  msg.data_type = TASK_TDT_UINT8;
  msg.function = TASK_TFC_READ;
  f = transact(&msg, &answer);
  CHECK(f == 0 && answer.data_cnt == sizeof nd, "COM_Node_Diag: msg.f %d", f);
  memcpy(&nd, answer.d, sizeof nd);
  CHECK(nd.usProfileNumber == 401 && nd.usAddInfo == 0x000F, "node 2's device type");
  CHECK(!nd.bNodeStatus_1.bNodeNoResponse && !nd.bNodeStatus_1.bPrmFault &&
            !nd.bNodeStatus_1.bDeactivated && nd.bNodeStatus_1.bGuardActive,
        "node 2's Nodestatus_1 bits");
  CHECK((answer.d[0] & (COM_ND_NO_RESPONSE | COM_ND_GUARD_ACTIVE)) == COM_ND_GUARD_ACTIVE,
        "Nodestatus_1 byte %#x", answer.d[0]);
  /* the last state the node's heartbeat reported: it may predate the node's start */
  CHECK(nd.bNodeState == COM_ND_STATE_OPERATIONAL || nd.bNodeState == COM_ND_STATE_PREOPERATIONAL,
        "node 2's Node_state %d", nd.bNodeState);
  printf("node diagnostics: node 2 profile %d, Nodestatus_1 %#x, error %d\n",
         nd.usProfileNumber, answer.d[0], nd.bActualError);

  /* NMT: stop node 2 and start it again */
  nmt(NMT_STOP_REMOTE_NODE, 2, 0);
  nmt(NMT_START_REMOTE_NODE, 2, 1);
  printf("NMT: node 2 stopped and started again\n");

  CHECK((rc = DevExitBoard(BOARD)) == DRV_NO_ERROR, "DevExitBoard: %d", rc);
  CHECK((rc = DevCloseDriver()) == DRV_NO_ERROR, "DevCloseDriver: %d", rc);
  printf("operative: all steps done\n");
  return 0;
}
