/*
 * com_user.h - the CANopen master card's messages and structures (cifemu's libcif).
 *
 * Written by the cifemu project from the seed manual ("CANopen Master Protocol
 * Interface"): task numbers, the CAN task's message codes, the protocol
 * parameters (Task2Parameter), COM_DIAGNOSTICS (Task2State), the node
 * diagnostic of COM_Node_Diag, the node and bus parameter records of
 * COM_Download, and the telegram header of COM_Shared_Memory. This is what
 * Hilscher's unpublished COM_USER.H held. Codes 110..117 are cifemu's own
 * ([ours], docs/card-commands.md). Every number is checked against dpm/.
 *
 * The seed writes `unsigned long` for 32-bit fields; they are fixed 32-bit here
 * (CIFEMU_U32), so the records keep their sizes on 64-bit systems.
 */
#ifndef CIFEMU_COM_USER_H_INCLUDED
#define CIFEMU_COM_USER_H_INCLUDED

#include "rcs_user.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef unsigned int CIFEMU_U32;

/* msg.rx / msg.tx */
#define COM_TASK_RCS               0
#define COM_TASK_PLC               2
#define COM_TASK_CAN               3
#define COM_TASK_USER              16

/* PLC task (msg.rx 2) */
#define COM_Shared_Memory          17

/* CAN task (msg.rx 3) */
#define COM_Get_Configuration      15
#define COM_Send_CANMsg_Transparent 65
#define COM_Receive_CANMsg_Transparent 65
#define COM_Node_Diag              66
#define COM_Start_Seq              67
#define COM_Download               68
#define COM_End_Seq                69
#define COM_SDO_Up_Download        74
#define COM_Upload                 80
#define COM_Reset_Err_Event        81
#define COM_CfgRx_Layer2           82
#define COM_Rx_CAN_Layer2          83
#define COM_Tx_CAN_Layer2          84
#define COM_NMT_Module_Protocol    96
#define COM_Set_SDO_Timeout        110 /* [ours] */
#define COM_Set_Guarding           111 /* [ours] */
#define COM_Set_Heartbeat_Consumer 112 /* [ours] */
#define COM_Set_Emcy_Consumer      113 /* [ours] */
#define COM_Set_Heartbeat_Producer 114 /* [ours] */
#define COM_Set_Node_ID            115 /* [ours] */
#define COM_Bootup_Forwarding      116 /* [ours] */
#define COM_Bootup_Indication      117 /* [ours] */

/* COM_Download / COM_Upload Area_Code */
#define COM_AREA_BUS_PARAMETER     127
#define COM_AREA_EXT_BUS_PARAMETER 128
#define COM_MAX_LEN_DATA_UNIT      240
#define COM_SDO_MAX_DATA           247

/* COM_NMT_Module_Protocol d[0] */
#define NMT_START_REMOTE_NODE      0x01
#define NMT_STOP_REMOTE_NODE       0x02
#define NMT_ENTER_PREOPERATIONAL   0x80
#define NMT_RESET_NODE             0x81
#define NMT_RESET_COMMUNICATION    0x82

/* COM_PLC_PARAMETER.bMode */
#define CANM_SET_MODE_BUFFERED_DEVICE_CONTROLLED 1
#define CANM_SET_MODE_UNCONTROLLED              2
#define CANM_SET_MODE_BUFFERED_HOST_CONTROLLED  3

/* COM_DIAGNOSTICS.bCAN_State */
#define CAN_STATE_OFFLINE          0x00
#define CAN_STATE_STOP             0x40
#define CAN_STATE_CLEAR            0x80
#define CAN_STATE_OPERATE          0xC0
/* COM_DIAGNOSTICS.tError.bErr_rem_adr when the device itself reports */
#define COM_ERR_DEVICE_ADR         255

/* COM_ND_DIAGNOSTICS.bNodeStatus_1, as a byte */
#define COM_ND_NO_RESPONSE         0x01
#define COM_ND_EMCY_BUFF_OVFL      0x02
#define COM_ND_PRM_FAULT           0x04
#define COM_ND_GUARD_ACTIVE        0x08
#define COM_ND_DEACT               0x80
/* COM_ND_DIAGNOSTICS.bNodeState (node guarding) */
#define COM_ND_STATE_DISCONNECTED  1
#define COM_ND_STATE_CONNECTING    2
#define COM_ND_STATE_PREPARING     3
#define COM_ND_STATE_PREPARED      4
#define COM_ND_STATE_OPERATIONAL   5
#define COM_ND_STATE_PREOPERATIONAL 127

/* COM_ND_PRM_HEADER.bNd_Flag and bitConfigNdState (a set bit skips that step) */
#define COM_ND_FLAG_HRTBT          0x40
#define COM_ND_FLAG_ACTIVE         0x80
#define COM_CFG_RESET              0x01
#define COM_CFG_DEVICE             0x02
#define COM_CFG_GUARD              0x04
#define COM_CFG_SYNC               0x08
#define COM_CFG_EMCY               0x10
#define COM_CFG_SDO                0x20
#define COM_CFG_START              0x40
#define COM_CFG_TXRXPDO            0x80

/* COM_PDO_DATA.bLength */
#define MSK_LENGTH                 0x7f
#define MSK_WORD_PDO               0x80

/* BUS_CAN.Baud_rate, Auto_Clear, Intel_Motorola */
#define COM_BAUD_10                8
#define COM_BAUD_20                7
#define COM_BAUD_50                6
#define COM_BAUD_100               5
#define COM_BAUD_125               4
#define COM_BAUD_250               3
#define COM_BAUD_500               2
#define COM_BAUD_800               1
#define COM_BAUD_1000              0
#define ACLR_INACTIVE              0
#define ACLR_ACTIVE                1
#define INTEL                      0
#define MOTOROLA                   1

#pragma pack(push, 1)

/* Task2Parameter (seed 2): DevPutTaskParameter(board, 2, 3, &param) */
typedef struct COM_PLC_PARAMETERtag {
  unsigned char  bMode;
  unsigned short usWatchDogTime;   /* ms; 0 = no host supervision */
  unsigned char  abReservedA[5];
  unsigned char  abReservedB[8];
} COM_PLC_PARAMETER;

/* Connection status bits (seed 3): DevReadWriteDPMRaw(board, 2, 0x2F0, 16, &status) */
typedef struct COM_NODE_CONN_STATUStag {
  unsigned char abConnStatus[16];  /* bit n = node n */
} COM_NODE_CONN_STATUS;

/* Task2State (seed 4): DevGetTaskState(board, 2, 64, &diag) */
typedef struct COM_DIAGNOSTICStag {
  struct {
    unsigned char bCtrl     : 1;
    unsigned char bAClr     : 1;
    unsigned char bNonExch  : 1;
    unsigned char bFatal    : 1;
    unsigned char bEvent    : 1;
    unsigned char bNRdy     : 1;
    unsigned char bTOut     : 1;
    unsigned char bReserved : 1;
  } bGlobalBits;
  unsigned char bCAN_State;
  struct {
    unsigned char bErr_rem_adr;
    unsigned char bErr_event;
  } tError;
  unsigned short usBus_Error_Cnt;
  unsigned short usBus_Off_Cnt;
  unsigned short usMsg_Time_Out;
  unsigned short usRx_Overflow;
  unsigned char  abReserved[4];
  unsigned char  abNd_cfg[16];
  unsigned char  abNd_state[16];
  unsigned char  abNd_diag[16];
} COM_DIAGNOSTICS;

/* The data of a COM_Node_Diag answer, after the telegram header (seed 5.2.7). The field
   names known from legacy programs (bNodeStatus_1's bits, bNodeState, bActualError) are
   theirs; the seed's Nodestatus_1 byte is also COM_ND_NO_RESPONSE ... COM_ND_DEACT. */
typedef struct COM_ND_DIAGNOSTICStag {
  struct {
    unsigned char bNodeNoResponse   : 1; /* node not responding */
    unsigned char bEmcyBuffOverflow : 1; /* emergency buffer overflow */
    unsigned char bPrmFault         : 1; /* master and node configuration differ */
    unsigned char bGuardActive      : 1; /* guarding (or heartbeat) supervises the node */
    unsigned char bReserved         : 3;
    unsigned char bDeactivated      : 1; /* node deactivated, not handled by the master */
  } bNodeStatus_1;
  unsigned short usAddInfo;        /* object 1000h, high word */
  unsigned short usProfileNumber;  /* object 1000h, low word */
  unsigned char  bNodeState;       /* COM_ND_STATE_* from node guarding */
  unsigned char  bActualError;     /* an Err_Event number (seed 4.3) */
  unsigned char  bEmcyEntries;
  unsigned char  abEmcyData[40];   /* five 8-byte emergency messages */
} COM_ND_DIAGNOSTICS;

/* COM_Download / COM_Upload / COM_Start_Seq / COM_End_Seq data (seed 5.2.3 - 5.2.6) */
typedef struct COM_DOWNLOAD_REQUESTtag {
  unsigned char  bReq_Adr;
  unsigned char  bArea_Code;       /* node 1..126, 127 bus, 128 extended bus parameters */
  unsigned short usAdd_Offset;
  unsigned char  abData[COM_MAX_LEN_DATA_UNIT];
} COM_DOWNLOAD_REQUEST;

typedef struct COM_UPLOAD_REQUESTtag {
  unsigned char  bReq_Adr;
  unsigned char  bArea_Code;
  unsigned short usAdd_Offset;
  unsigned char  bData_Len;
} COM_UPLOAD_REQUEST;

typedef struct COM_START_SEQ_REQUESTtag {
  unsigned char  bReq_Adr;
  unsigned char  bArea_Code;
  unsigned short usTimeout;
} COM_START_SEQ_REQUEST;

typedef struct COM_START_SEQ_CONFIRMtag {
  unsigned char bMax_Len_Data_Unit;
} COM_START_SEQ_CONFIRM;

typedef struct COM_END_SEQ_REQUESTtag {
  unsigned char bReq_Adr;
} COM_END_SEQ_REQUEST;

/* Node parameter data set (seed 5.2.5.1.1): header, then the SDO list, the PDO list
 * and the ADD-tab, each led by its length word (which counts itself). */
typedef struct COM_ND_PRM_HEADERtag {
  unsigned short usNodeParaLen;
  unsigned char  bNd_Flag;
  unsigned short usAddTypeInfo;
  unsigned short usDevProfNum;
  unsigned short usCobIDEmcy;
  unsigned short usCobIDGuard;
  unsigned short usGuardTime;
  unsigned char  bLifeTimeFactor;
  unsigned char  bitConfigNdState;
  unsigned char  abReserved[1];
} COM_ND_PRM_HEADER;

typedef struct COM_SDO_CFG_DATAtag {
  unsigned short usIndex;
  unsigned char  bSubindex;
  unsigned short bLength;          /* a word, as the seed's table says */
  unsigned char  abSdoValue[4];
} COM_SDO_CFG_DATA;

typedef struct COM_PDO_DATAtag {
  unsigned char  bTypeOfPdo;       /* 0 RXPDO (outputs), else TXPDO (inputs) */
  unsigned char  bLength;          /* MSK_LENGTH, MSK_WORD_PDO */
  unsigned short usPdoCOBId;
  unsigned char  bTransType;
  unsigned short usInhibitCycle;
} COM_PDO_DATA;

typedef struct COM_ND_PRM_ADD_TABtag {
  unsigned short usAddTabLen;
  unsigned char  bInputCount;
  unsigned char  bOutputCount;
  unsigned short ausIOOffsets[1];  /* inputs first, then outputs: bInputCount + bOutputCount */
} COM_ND_PRM_ADD_TAB;

/* Bus parameter data set (seed 5.2.5.4.1): downloading it starts the network */
typedef struct BUS_CANtag {
  unsigned char  Baud_rate;
  unsigned short COB_ID_SYNC;
  unsigned short SYNC_Timer;
  unsigned char  Auto_Clear;
  unsigned char  Intel_Motorola;
} BUS_CAN;

/* Extended bus parameter data set (seed 5.2.5.3) */
typedef struct BUS_CAN_EXTtag {
  struct {
    unsigned char bi11Bit29BitSelector : 1;
    unsigned char biNoGobalStartNode   : 1;
    unsigned char biReserved           : 6;
  } bExtendedState;
  CIFEMU_U32     ulAcceptCode;
  CIFEMU_U32     ulAcceptMask;
  unsigned char  bNodeID;
  unsigned short usProducerHeartbeatTime;
  unsigned char  bReserved;
  CIFEMU_U32     ulReserved[7];
} BUS_CAN_EXT;

/* COM_NMT_Module_Protocol data (seed 5.2.9) */
typedef struct COM_NMT_REQUESTtag {
  unsigned char bNmtCmd;           /* NMT_START_REMOTE_NODE ... */
  unsigned char bNodeID;           /* 0 = all nodes */
} COM_NMT_REQUEST;

/* The telegram header of COM_Shared_Memory, COM_Node_Diag and COM_SDO_Up_Download */
typedef struct COM_TELEGRAM_HEADERtag {
  unsigned char  device_adr;       /* node (Node_Diag, SDO); 0 for Shared_Memory */
  unsigned char  data_area;        /* Shared_Memory: 0 by function, 1 RcvPd, 2 SndPd */
  unsigned short data_adr;         /* offset; SDO: object index */
  unsigned char  data_idx;         /* bit position; SDO: subindex */
  unsigned char  data_cnt;
  unsigned char  data_type;        /* TASK_TDT_* */
  unsigned char  function;         /* TASK_TFC_READ / TASK_TFC_WRITE */
} COM_TELEGRAM_HEADER;

#define COM_SHM_AREA_BY_FUNCTION   0
#define COM_SHM_AREA_RECEIVE       1
#define COM_SHM_AREA_SEND          2

#pragma pack(pop)

RCS_SIZE_ASSERT(COM_PLC_PARAMETER, 16);
RCS_SIZE_ASSERT(COM_NODE_CONN_STATUS, 16);
RCS_SIZE_ASSERT(COM_DIAGNOSTICS, 64);
RCS_SIZE_ASSERT(COM_ND_DIAGNOSTICS, 48);
RCS_SIZE_ASSERT(COM_DOWNLOAD_REQUEST, 244);
RCS_SIZE_ASSERT(COM_UPLOAD_REQUEST, 5);
RCS_SIZE_ASSERT(COM_START_SEQ_REQUEST, 4);
RCS_SIZE_ASSERT(COM_ND_PRM_HEADER, 16);
RCS_SIZE_ASSERT(COM_SDO_CFG_DATA, 9);
RCS_SIZE_ASSERT(COM_PDO_DATA, 7);
RCS_SIZE_ASSERT(COM_ND_PRM_ADD_TAB, 6);
RCS_SIZE_ASSERT(BUS_CAN, 7);
RCS_SIZE_ASSERT(BUS_CAN_EXT, 41);
RCS_SIZE_ASSERT(COM_NMT_REQUEST, 2);
RCS_SIZE_ASSERT(COM_TELEGRAM_HEADER, 8);

#ifdef __cplusplus
}
#endif

#endif /* CIFEMU_COM_USER_H_INCLUDED */
