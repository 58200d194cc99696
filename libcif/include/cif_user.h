/*
 * cif_user.h - the CIF device driver API for Linux host programs (cifemu's libcif).
 *
 * Written by the cifemu project from the published facts of Hilscher's Linux
 * driver API: the same prototypes, constants, structure and field names, so a
 * legacy program compiles unchanged and runs against an emulated card
 * (`cifemu firmware`). The calls work on the card's dual-port memory image,
 * <dir>/board<N>.dpm, with <dir> = $CIF_DPM_DIR or /dev/shm/cif.
 *
 * Structures are packed (no padding).
 *
 * The rule for `ul` fields [ours]: every `ul...` FIELD of a structure is a fixed
 * 32-bit unsigned integer (CIF_UL32, an unsigned int), on 32-bit and 64-bit
 * systems alike. The structures are then byte-identical to the card's image and
 * to the original 32-bit ABI, and their sizes are the documented ones (asserted
 * below). A program that prints such a field with "%ld" gets a format warning
 * only. The scalar ARGUMENTS ulTimeout and DevDownload's byte counter keep
 * `unsigned long`, as in the original prototypes.
 */
#ifndef CIFUSER_H_INCLUDED
#define CIFUSER_H_INCLUDED

#ifdef __cplusplus
extern "C" {
#endif

#ifndef PACKED
#define PACKED __attribute__((packed))
#endif

typedef unsigned int CIF_UL32; /* 32 bits on every Linux ABI: the `ul` fields */

/* ---- limits and modes ---------------------------------------------------- */
#define MAX_DEV_BOARDS           4
#define DRV_RCS_ERROR_OFFSET     1000 /* a task's refusal returns 1000 + msg.f */

#define COLDSTART                2
#define WARMSTART                3
#define BOOTSTART                4

#define DEVICE_MBX_EMPTY         0
#define DEVICE_MBX_FULL          1
#define HOST_MBX_EMPTY           0
#define HOST_MBX_FULL            1

#define WATCHDOG_STOP            0
#define WATCHDOG_START           1

#define HOST_NOT_READY           0
#define HOST_READY               1

#define PARAMETER_READ           1
#define PARAMETER_WRITE          2

#define SPECIAL_CONTROL_CLEAR    0
#define SPECIAL_CONTROL_SET      1

#define FIRMWARE_DOWNLOAD        1
#define CONFIGURATION_DOWNLOAD   2

#define POLLING_MODE             0
#define INTERRUPT_MODE           1

/* DevGetInfo areas */
#define GET_DRIVER_INFO          1
#define GET_VERSION_INFO         2
#define GET_FIRMWARE_INFO        3
#define GET_TASK_INFO            4
#define GET_RCS_INFO             5
#define GET_DEV_INFO             6
#define GET_IO_INFO              7
#define GET_IO_SEND_DATA         8

/* DevExchangeIOErr: COMSTATE.usMode */
#define STATE_ERR_NON            0
#define STATE_ERR                1
#define STATE_MODE_2             2
#define STATE_MODE_3             3
#define STATE_MODE_4             4

/* DRIVERINFO.bLastFunction */
#define FKT_OPEN                 1
#define FKT_CLOSE                2
#define FKT_READ                 3
#define FKT_WRITE                4
#define FKT_IO                   5

/* DRIVERINFO.bReadState / bWriteState */
#define STATE_IN                 1
#define STATE_WAIT               2
#define STATE_OUT                3
#define STATE_IN_IRQ             4

/* ---- return codes -------------------------------------------------------- */
#define DRV_NO_ERROR                0
#define DRV_BOARD_NOT_INITIALIZED  -1
#define DRV_INIT_STATE_ERROR       -2
#define DRV_READ_STATE_ERROR       -3
#define DRV_CMD_ACTIVE             -4
#define DRV_PARAMETER_UNKNOWN      -5
#define DRV_WRONG_DRIVER_VERSION   -6
#define DRV_PCI_SET_CONFIG_MODE    -7
#define DRV_PCI_READ_DPM_LENGTH    -8
#define DRV_PCI_SET_RUN_MODE       -9

#define DRV_DEV_DPM_ACCESS_ERROR   -10
#define DRV_DEV_NOT_READY          -11
#define DRV_DEV_NOT_RUNNING        -12
#define DRV_DEV_WATCHDOG_FAILED    -13
#define DRV_DEV_OS_VERSION_ERROR   -14
#define DRV_DEV_SYSERR             -15
#define DRV_DEV_MAILBOX_FULL       -16
#define DRV_DEV_PUT_TIMEOUT        -17
#define DRV_DEV_GET_TIMEOUT        -18
#define DRV_DEV_GET_NO_MESSAGE     -19
#define DRV_DEV_RESET_TIMEOUT      -20
#define DRV_DEV_NO_COM_FLAG        -21
#define DRV_DEV_EXCHANGE_FAILED    -22
#define DRV_DEV_EXCHANGE_TIMEOUT   -23
#define DRV_DEV_COM_MODE_UNKNOWN   -24
#define DRV_DEV_FUNCTION_FAILED    -25
#define DRV_DEV_DPMSIZE_MISMATCH   -26
#define DRV_DEV_STATE_MODE_UNKNOWN -27

#define DRV_USR_OPEN_ERROR         -30
#define DRV_USR_INIT_DRV_ERROR     -31
#define DRV_USR_NOT_INITIALIZED    -32
#define DRV_USR_COMM_ERR           -33
#define DRV_USR_DEV_NUMBER_INVALID -34
#define DRV_USR_INFO_AREA_INVALID  -35
#define DRV_USR_NUMBER_INVALID     -36
#define DRV_USR_MODE_INVALID       -37
#define DRV_USR_MSG_BUF_NULL_PTR   -38
#define DRV_USR_MSG_BUF_TOO_SHORT  -39
#define DRV_USR_SIZE_INVALID       -40
#define DRV_USR_SIZE_ZERO          -42
#define DRV_USR_SIZE_TOO_LONG      -43
#define DRV_USR_DEV_PTR_NULL       -44
#define DRV_USR_BUF_PTR_NULL       -45
#define DRV_USR_SENDSIZE_TOO_LONG  -46
#define DRV_USR_RECVSIZE_TOO_LONG  -47
#define DRV_USR_SENDBUF_PTR_NULL   -48
#define DRV_USR_RECVBUF_PTR_NULL   -49

#define DRV_DEV_NO_VIRTUAL_MEM     -60 /* Linux only */
#define DRV_DEV_UNMAP_VIRTUAL_MEM  -61 /* Linux only */
#define DRV_DEV_REQUEST_IRQ_FAILED -62 /* Linux only */

#define DRV_USR_FILE_OPEN_FAILED   -100
#define DRV_USR_FILE_SIZE_ZERO     -101
#define DRV_USR_FILE_NO_MEMORY     -102
#define DRV_USR_FILE_READ_FAILED   -103
#define DRV_USR_INVALID_FILETYPE   -104
#define DRV_USR_FILENAME_INVALID   -105

/* ---- structures ---------------------------------------------------------- */
#pragma pack(push, 1)

typedef struct tagMSG_STRUC {
  unsigned char rx;   /* receiver task */
  unsigned char tx;   /* transmitter task */
  unsigned char ln;   /* number of data bytes */
  unsigned char nr;   /* message number */
  unsigned char a;    /* answer: the command answered */
  unsigned char f;    /* fault */
  unsigned char b;    /* command */
  unsigned char e;    /* extension */
  unsigned char data[255];
  unsigned char dummy[25];
} MSG_STRUC;

typedef struct tagIOINFO {
  unsigned char bComBit;
  unsigned char bIOExchangeMode;
  CIF_UL32      ulIOExchangeCnt;
} IOINFO;

typedef struct tagVERSIONINFO {
  CIF_UL32      ulDate;
  CIF_UL32      ulDeviceNo;
  CIF_UL32      ulSerialNo;
  CIF_UL32      ulReserved;
  unsigned char abPcOsName0[4];
  unsigned char abPcOsName1[4];
  unsigned char abPcOsName2[4];
  unsigned char abOemIdentifier[4];
} VERSIONINFO;

typedef struct tagFIRMWAREINFO {
  unsigned char abFirmwareName[16];
  unsigned char abFirmwareVersion[16];
} FIRMWAREINFO;

typedef struct tagTASKSTATE {
  unsigned char abTaskState[64];
} TASKSTATE;

typedef struct tagTASKPARAM {
  unsigned char abTaskParameter[64];
} TASKPARAM;

typedef struct tagRAWDATA {
  unsigned char abRawData[1022];
} RAWDATA;

typedef struct tagTASKINFO {
  struct {
    unsigned char  abTaskName[8];
    unsigned short usTaskVersion;
    unsigned char  bTaskCondition;
    unsigned char  abreserved[5];
  } tTaskInfo[7];
} TASKINFO;

typedef struct tagRCSINFO {
  unsigned short usRcsVersion;
  unsigned char  bRcsError;
  unsigned char  bHostWatchDog;
  unsigned char  bDevWatchDog;
  unsigned char  bSegmentCount;
  unsigned char  bDeviceAdress;
  unsigned char  bDriverType;
} RCSINFO;

typedef struct tagDEVINFO {
  unsigned char bDpmSize;
  unsigned char bDevType;
  unsigned char bDevModel;
  unsigned char abDevIdentifier[3];
} DEVINFO;

typedef struct tagBOARD_INFO {
  unsigned char abDriverVersion[16];
  struct {
    unsigned short usBoard;
    unsigned short usAvailable;
    CIF_UL32       ulPhysicalAddress;
    unsigned short usIrq;
  } tBoard[MAX_DEV_BOARDS];
  unsigned short usBoards_detected;
} BOARD_INFO;

typedef struct tagDRIVERINFO {
  CIF_UL32      ulOpenCnt;
  CIF_UL32      CloseCnt;
  CIF_UL32      ulReadCnt;
  CIF_UL32      ulWriteCnt;
  CIF_UL32      ulIRQCnt;
  unsigned char bInitMsgFlag;
  unsigned char bReadMsgFlag;
  unsigned char bWriteMsgFlag;
  unsigned char bLastFunction;
  unsigned char bWriteState;
  unsigned char bReadState;
  unsigned char bHostFlags;
  unsigned char bMyDevFlags;
  unsigned char bExIOFlag;
  CIF_UL32      ulExIOCnt;
} DRIVERINFO;

typedef struct tagBOARD_INFOEX {
  unsigned char abDriverVersion[16];
  struct {
    unsigned short usBoard;
    unsigned short usAvailable;
    CIF_UL32       ulPhysicalAddress;
    unsigned short usIrq;
    DRIVERINFO     tDriverInfo;
    FIRMWAREINFO   tFirmware;
    DEVINFO        tDeviceInfo;
    RCSINFO        tRcsInfo;
    VERSIONINFO    tVersion;
  } tBoard[MAX_DEV_BOARDS];
} BOARD_INFOEX;

typedef struct tagCOMSTATE {
  unsigned short usMode;
  unsigned short usStateFlag;
  unsigned char  abState[64];
} COMSTATE;

#pragma pack(pop)

/* The documented sizes, checked by every compiler that includes this header. */
#if defined(__cplusplus) && __cplusplus >= 201103L
#define CIF_SIZE_ASSERT(t, n) static_assert(sizeof(t) == (n), #t " must be " #n " bytes")
#elif defined(__STDC_VERSION__) && __STDC_VERSION__ >= 201112L
#define CIF_SIZE_ASSERT(t, n) _Static_assert(sizeof(t) == (n), #t " must be " #n " bytes")
#else
#define CIF_SIZE_ASSERT_(t, n, l) typedef char cif_size_assert_##l[(sizeof(t) == (n)) ? 1 : -1]
#define CIF_SIZE_ASSERT__(t, n, l) CIF_SIZE_ASSERT_(t, n, l)
#define CIF_SIZE_ASSERT(t, n) CIF_SIZE_ASSERT__(t, n, __LINE__)
#endif
CIF_SIZE_ASSERT(MSG_STRUC, 288);
CIF_SIZE_ASSERT(IOINFO, 6);
CIF_SIZE_ASSERT(VERSIONINFO, 32);
CIF_SIZE_ASSERT(FIRMWAREINFO, 32);
CIF_SIZE_ASSERT(TASKSTATE, 64);
CIF_SIZE_ASSERT(TASKPARAM, 64);
CIF_SIZE_ASSERT(RAWDATA, 1022);
CIF_SIZE_ASSERT(TASKINFO, 112);
CIF_SIZE_ASSERT(RCSINFO, 8);
CIF_SIZE_ASSERT(DEVINFO, 6);
CIF_SIZE_ASSERT(BOARD_INFO, 58);
CIF_SIZE_ASSERT(DRIVERINFO, 33);
CIF_SIZE_ASSERT(BOARD_INFOEX, 500);
CIF_SIZE_ASSERT(COMSTATE, 68);

/* ---- functions (all return a DRV_* code; timeouts in milliseconds) -------- */
short DevOpenDriver(void);
short DevCloseDriver(void);
short DevGetBoardInfo(BOARD_INFO *pvData);
short DevGetBoardInfoEx(void *pvData);
short DevSetOpMode(unsigned short usBoard, unsigned short usMode, unsigned short *usIrq);
short DevInitBoard(unsigned short usDevNumber);
short DevExitBoard(unsigned short usDevNumber);
short DevPutTaskParameter(unsigned short usDevNumber, unsigned short usNumber,
                          unsigned short usSize, void *pvData);
short DevGetTaskParameter(unsigned short usDevNumber, unsigned short usNumber,
                          unsigned short usSize, void *pvData);
short DevReset(unsigned short usDevNumber, unsigned short usMode, unsigned long ulTimeout);
short DevPutMessage(unsigned short usDevNumber, MSG_STRUC *ptMessage, unsigned long ulTimeout);
short DevGetMessage(unsigned short usDevNumber, unsigned short usSize, MSG_STRUC *ptMessage,
                    unsigned long ulTimeout);
short DevGetTaskState(unsigned short usDevNumber, unsigned short usNumber,
                      unsigned short usSize, void *pvData);
short DevGetMBXState(unsigned short usDevNumber, unsigned short *pusDevMBXState,
                     unsigned short *pusHostMBXState);
short DevTriggerWatchDog(unsigned short usDevNumber, unsigned short usFunction,
                         unsigned short *usDevWatchDog);
short DevGetInfo(unsigned short usDevNumber, unsigned short usFunction, unsigned short usSize,
                 void *pvData);
short DevExchangeIO(unsigned short usDevNumber, unsigned short usSendOffset,
                    unsigned short usSendSize, void *pvSendData,
                    unsigned short usReceiveOffset, unsigned short usReceiveSize,
                    void *pvReceiveData, unsigned long ulTimeout);
short DevExchangeIOEx(unsigned short usDevNumber, unsigned short usMode,
                      unsigned short usSendOffset, unsigned short usSendSize, void *pvSendData,
                      unsigned short usReceiveOffset, unsigned short usReceiveSize,
                      void *pvReceiveData, unsigned long ulTimeout);
short DevExchangeIOErr(unsigned short usDevNumber, unsigned short usSendOffset,
                       unsigned short usSendSize, void *pvSendData,
                       unsigned short usReceiveOffset, unsigned short usReceiveSize,
                       void *pvReceiveData, COMSTATE *ptState, unsigned long ulTimeout);
short DevReadSendData(unsigned short usDevNumber, unsigned short usOffset, unsigned short usSize,
                      void *pvData);
short DevSetHostState(unsigned short usDevNumber, unsigned short usMode, unsigned long ulTimeout);
short DevExtendedData(unsigned short usDevNumber, unsigned short usMode, unsigned short usSize,
                      void *pvData);
short DevGetMBXData(unsigned short usDevNumber, unsigned short usHostSize, void *pvHostData,
                    unsigned short usDevSize, void *pvDevData);
short DevReadWriteDPMRaw(unsigned short usDevNumber, unsigned short usMode,
                         unsigned short usOffset, unsigned short usSize, void *pvData);
short DevReadWriteDPMData(unsigned short usDevNumber, unsigned short usMode,
                          unsigned short usOffset, unsigned short usSize, void *pvData);
short DevSpecialControl(unsigned short usDevNumber, unsigned short usMode,
                        unsigned short *pusCtrlAck);
short DevDownload(unsigned short usDevNumber, unsigned short usMode,
                  unsigned char *pszFileName, unsigned long *pdwBytes);

/* The real API object's descriptor of /dev/cif; here 0 while the driver is open, else -1. */
extern int hDevDrv;

#ifdef __cplusplus
}
#endif

#endif /* CIFUSER_H_INCLUDED */
