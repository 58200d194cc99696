/*
 * dpm.h - the 8 KiB image's offsets and flag bits, and the request the card does not
 * answer, as libcif uses them.
 *
 * The numbers are those of the project's card header (dpm/layout.py, dpm/flags.py,
 * dpm/commands.py); tests/test_libcif_headers.py checks each one against it.
 */
#ifndef CIFEMU_DPM_H
#define CIFEMU_DPM_H

#define DPM_SIZE          8192
#define IO_AREA_SIZE      3584 /* (DPM_SIZE - 1024) / 2 */
#define LAST_KB           0x1C00
#define RAW_AREA_LIMIT    1022 /* DevReadWriteDPMRaw stops short of the flags */
#define MSG_BUFFER_SIZE   288
#define TASK_AREA_SIZE    64

#define OFS_SND_PD           0x0000
#define OFS_RCV_PD           0x0E00
#define OFS_DEV_MBX          0x1C00
#define OFS_VERSION_INFO     0x1D20
#define OFS_PC_MBX           0x1D40
#define OFS_FIRMWARE_INFO    0x1E60
#define OFS_TASK1_PARAMETER  0x1E80
#define OFS_TASK2_PARAMETER  0x1EC0
#define OFS_TASK1_STATE      0x1F00
#define OFS_TASK2_STATE      0x1F40
#define OFS_TASK_INFO        0x1F80
#define OFS_RCS_INFO         0x1FF0
#define OFS_RCS_ERROR        0x1FF2
#define OFS_HOST_WATCHDOG    0x1FF3
#define OFS_DEV_WATCHDOG     0x1FF4
#define OFS_DRIVER_TYPE      0x1FF7
#define OFS_DEV_INFO         0x1FF8
#define OFS_DPM_SIZE         0x1FF8
#define OFS_DEV_IDENTIFIER   0x1FFB
#define OFS_HOST_FLAGS       0x1FFE
#define OFS_DEV_FLAGS        0x1FFF

/* HostFlags, written by the device */
#define FL_HOSTCOM   0x01
#define FL_DEVACK    0x02
#define FL_PDACK     0x04
#define FL_STATECOM  0x08
#define FL_SPCACK    0x10
#define FL_COM       0x20
#define FL_RUN       0x40
#define FL_READY     0x80
/* DevFlags, written by the host */
#define FL_HOSTACK   0x01
#define FL_DEVCOM    0x02
#define FL_PDCOM     0x04
#define FL_STATEACK  0x08
#define FL_SPCCOM    0x10
#define FL_NOTREADY  0x20
#define FL_INIT      0x40
#define FL_RESET     0x80

/* Handshake channels: the bit position both sides toggle (pending while they differ) */
#define CH_HOST_MBX  0x01
#define CH_DEV_MBX   0x02
#define CH_PD        0x04
#define CH_STATE     0x08

/* The request the card does not answer, whatever msg.e (dpm/commands.py UNANSWERED, seed
   5.3.1): COM_Tx_CAN_Layer2 to the CAN task. Like one sent with msg.e NAK it is answered
   only when it fails, so the ledger awaits no answer to it (chanlock.c). */
#define UNANSWERED_RX 3
#define UNANSWERED_B  84

#endif
