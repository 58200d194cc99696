/*
 * rcsdef.h - RCS constants of the CIF card's operating system (cifemu's libcif).
 *
 * Written by the cifemu project: the task numbers, RCS commands, message
 * extension masks and load-function modes a legacy host program includes.
 * Every number is checked against the project's card header (dpm/) by a test.
 */
#ifndef CIFEMU_RCSDEF_H_INCLUDED
#define CIFEMU_RCSDEF_H_INCLUDED

#ifndef FIRMWARE_DOWNLOAD
#define FIRMWARE_DOWNLOAD          1
#endif
#ifndef CONFIGURATION_DOWNLOAD
#define CONFIGURATION_DOWNLOAD     2
#endif

/* msg.rx / msg.tx */
#define RCS_TASK                   0x00
#define PLC_TASK                   0x02
#define MSG_SYSTEM_TX              0xFF

/* RCS commands (msg.b to RCS_TASK) */
#define RCS_B_SYSFKT               1
#define RCS_B_LOADFKT              6

/* msg.e: answer suppression and the sequence of split transfers */
#define RCS_NAK_MSK                2
#define RCS_NORM_MSK               0
#define RCS_FIRST_MSK              4
#define RCS_CONT_MSK               8
#define RCS_LAST_MSK               0x0C
#define RCS_SEQ_MSK                0x0C

/* RCS_B_LOADFKT modes (d[0]) */
#define MODE_UPLOAD_DBM            2
#define MODE_DOWNLOAD_DBM          3
#define MODE_DEL_FLASH             4
#define MODE_GET_FLASH_DIR         5

#endif /* CIFEMU_RCSDEF_H_INCLUDED */
