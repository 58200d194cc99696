/*
 * asc_user.h - parameters of the ASCII protocol task of other CIF cards (cifemu's libcif).
 *
 * The emulated card is a CANopen master and has no ASCII task; this header exists so that
 * legacy programs which include it (Hilscher's demo programs, some CANopen hosts) compile
 * unchanged. Written by the cifemu project from the published names and types. Like the
 * Linux original, the structures keep the compiler's natural alignment; `ul` fields are
 * 32 bits, as in cif_user.h.
 */
#ifndef CIFEMU_ASC_USER_H_INCLUDED
#define CIFEMU_ASC_USER_H_INCLUDED

#define ASC_MODE_SLAVE              0
#define ASC_MODE_MASTER             1

#define ASC_ENDMODE_TIMEOUT         0
#define ASC_ENDMODE_ID              1
#define ASC_ENDMODE_QUITT           2
#define ASC_ENDMODE_ID_QUITT        3
#define ASC_ENDMODE_NUMBER          4
#define ASC_ENDMODE_DEFNUMBER       5

#define ASC_CHKSUM_NONE             0
#define ASC_CHKSUM_BIN7             1
#define ASC_CHKSUM_BIN8             2
#define ASC_CHKSUM_BCC              3
#define ASC_CHKSUM_BCC_ASCII        4

#define ASC_CHK_AREA_DATA_ONLY      0
#define ASC_CHK_AREA_DATA_STARTID   1
#define ASC_CHK_AREA_DATA_ENDID     2
#define ASC_CHK_AREA_FULL           3

#define ASC_FILTER_NONE             0
#define ASC_FILTER_DOUBLE_CHAR      1

#define ASC_TIMEOUT_NONE            0
#define ASC_TELEGRAM_LENGTH_ZERO    0
#define ASC_TELEGRAM_SEQUENZ_NONE   0

typedef struct ASC_PARAMETRtag {
  unsigned char  bScl;              /* serial line */
  unsigned char  bRtsControl;
  unsigned char  bBaudrate;
  unsigned char  bDataBits;
  unsigned char  bStopBits;
  unsigned char  bParityBit;
  unsigned char  bMode;             /* ASC_MODE_* */
  unsigned char  bEndMode;          /* ASC_ENDMODE_* */
  unsigned char  bCheckMode;        /* ASC_CHKSUM_* */
  unsigned char  bCheckArea;        /* ASC_CHK_AREA_* */
  unsigned char  bFilterMode;       /* ASC_FILTER_* */
  unsigned short usFilterCharacter;
  unsigned short usTelTimeout;
  unsigned short usStartTimeout;
  unsigned short usCharTimeout;
  unsigned char  bRetries;
  unsigned char  bErrorLed;
  unsigned char  bTelStartLen;
  unsigned char  bTelStart[8];
  unsigned char  bTelEndLen;
  unsigned char  bTelEnd[8];
  unsigned char  bTelAckLen;
  unsigned char  bTelAck[8];
  unsigned char  bTelNackLen;
  unsigned char  bTelNack[8];
  unsigned char  bTelDeviceLen;
  unsigned short usTelFollowTime;
} ASC_PARAMETER;

typedef struct ASC_STATEtag {
  unsigned char  bTaskState;
  unsigned int   ulTxCount;
  unsigned int   ulRxCount;
  unsigned short usTxErrorCount;
  unsigned short usRxErrorCount;
  unsigned short usErrorBits;
  unsigned char  bError;
} ASC_STATE;

#endif /* CIFEMU_ASC_USER_H_INCLUDED */
