/*
 * nvr_user.h - parameters of the 3964R protocol task of other CIF cards (cifemu's libcif).
 *
 * The emulated card is a CANopen master and has no 3964R task; this header exists so that
 * legacy programs which include it compile unchanged. Written by the cifemu project from
 * the published names and types; natural alignment as the Linux original, `ul` fields 32
 * bits as in cif_user.h.
 */
#ifndef CIFEMU_NVR_USER_H_INCLUDED
#define CIFEMU_NVR_USER_H_INCLUDED

#define NVR_MODE_MSB_LSB            0
#define NVR_MODE_LSB_MSB            1
#define NVR_MODE_BYTE               2
#define NVR_MODE_TRANSPARENT        3

typedef struct NVR_PARAMETRtag {
  unsigned char  bScl;              /* serial line */
  unsigned char  bRtsControl;
  unsigned char  bBaudrate;
  unsigned char  bDataBits;
  unsigned char  bStopBits;
  unsigned char  bParityBit;
  unsigned char  bPriority;
  unsigned short usTimeout;
  unsigned char  bReceiveMode;      /* NVR_MODE_* */
  unsigned char  bSendMode;         /* NVR_MODE_* */
  unsigned char  bErrorLed;
} NVR_PARAMETER;

typedef struct NVR_STATEtag {
  unsigned char  bTaskState;
  unsigned int   ulTxCount;
  unsigned int   ulRxCount;
  unsigned char  bTxRetryCount;
  unsigned char  bRxRetryCount;
  unsigned short usTxErrorCount;
  unsigned short usRxErrorCount;
  unsigned short usErrorBits;
  unsigned char  bError;
} NVR_STATE;

#endif /* CIFEMU_NVR_USER_H_INCLUDED */
