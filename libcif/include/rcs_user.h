/*
 * rcs_user.h - RCS message and telegram structures (cifemu's libcif).
 *
 * Written by the cifemu project. A message is an 8-byte header (rx tx ln nr
 * a f b e) and ln data bytes in a 288-byte segment; messages of the telegram
 * kind start their data with the 8-byte extended telegram header. Structures
 * are packed; every size is asserted. Numbers are checked against dpm/.
 */
#ifndef CIFEMU_RCS_USER_H_INCLUDED
#define CIFEMU_RCS_USER_H_INCLUDED

#ifdef __cplusplus
extern "C" {
#endif

#ifndef PACKED
#define PACKED __attribute__((packed))
#endif

/* msg.f of task answers (the numbers the emulated card's tasks use) */
#define TASK_F_OK                  0
#define TASK_F_MESSAGECOMMAND      152 /* unknown command */
#define TASK_F_DEVICE_ADR          161 /* remote address out of range */
#define TASK_F_DATA_AREA           162 /* illegal address area */
#define TASK_F_DATA_ADR            163 /* address + count overflow the buffer */
#define TASK_F_DATA_CNT            165 /* illegal data count */
#define TASK_F_DATA_TYPE           166 /* unknown data type */
#define TASK_F_FUNCTION            167 /* unknown function */
#define TASK_F_NOT_INITIALIZED     200 /* DEVICE is not configured */

/* msg.function of the telegram header */
#define TASK_TFC_READ              1
#define TASK_TFC_WRITE             2
#define TASK_TFC_QUERRY            3

/* msg.data_type of the telegram header */
#define TASK_TDT_UINT8             5
#define TASK_TDT_UINT16            6
#define TASK_TDT_STRING            10
#define TASK_TDT_BIT               14
#define TASK_TDT_IDF_MSK           0x80 /* Intel byte order */

#define RCS_SEGMENT_LEN            288
#define RCS_MESSAGEHEADER_LEN      8
#define RCS_TELEGRAMHEADER_LEN     8

#pragma pack(push, 1)

typedef struct RCS_MESSAGEHEADERtag {
  unsigned char rx, tx, ln, nr, a, f, b, e;
} RCS_MESSAGEHEADER;

typedef struct RCS_MESSAGEtag {
  unsigned char rx, tx, ln, nr, a, f, b, e;
  unsigned char d[RCS_SEGMENT_LEN - RCS_MESSAGEHEADER_LEN];
} RCS_MESSAGE;

typedef struct RCS_TELEGRAMHEADER_10tag {
  unsigned char  device_adr;
  unsigned char  data_area;
  unsigned short data_adr;
  unsigned char  data_idx;
  unsigned char  data_cnt;
  unsigned char  data_type;
  unsigned char  function;
} RCS_TELEGRAMHEADER_10;

typedef struct RCS_MESSAGETELEGRAMHEADER_10tag {
  unsigned char  rx, tx, ln, nr, a, f, b, e;
  unsigned char  device_adr;
  unsigned char  data_area;
  unsigned short data_adr;
  unsigned char  data_idx;
  unsigned char  data_cnt;
  unsigned char  data_type;
  unsigned char  function;
} RCS_MESSAGETELEGRAMHEADER_10;

typedef struct RCS_TELEGRAMHEADERDATA_10tag {
  unsigned char  device_adr;
  unsigned char  data_area;
  unsigned short data_adr;
  unsigned char  data_idx;
  unsigned char  data_cnt;
  unsigned char  data_type;
  unsigned char  function;
  unsigned char  d[RCS_SEGMENT_LEN - RCS_MESSAGEHEADER_LEN - RCS_TELEGRAMHEADER_LEN];
} RCS_TELEGRAMHEADERDATA_10;

typedef struct RCS_MESSAGETELEGRAM_10tag {
  unsigned char  rx, tx, ln, nr, a, f, b, e;
  unsigned char  device_adr;
  unsigned char  data_area;
  unsigned short data_adr;
  unsigned char  data_idx;
  unsigned char  data_cnt;
  unsigned char  data_type;
  unsigned char  function;
  unsigned char  d[RCS_SEGMENT_LEN - RCS_MESSAGEHEADER_LEN - RCS_TELEGRAMHEADER_LEN];
} RCS_MESSAGETELEGRAM_10;

#pragma pack(pop)

#if defined(__cplusplus) && __cplusplus >= 201103L
#define RCS_SIZE_ASSERT(t, n) static_assert(sizeof(t) == (n), #t " must be " #n " bytes")
#elif defined(__STDC_VERSION__) && __STDC_VERSION__ >= 201112L
#define RCS_SIZE_ASSERT(t, n) _Static_assert(sizeof(t) == (n), #t " must be " #n " bytes")
#else
#define RCS_SIZE_ASSERT_(t, n, l) typedef char rcs_size_assert_##l[(sizeof(t) == (n)) ? 1 : -1]
#define RCS_SIZE_ASSERT__(t, n, l) RCS_SIZE_ASSERT_(t, n, l)
#define RCS_SIZE_ASSERT(t, n) RCS_SIZE_ASSERT__(t, n, __LINE__)
#endif
RCS_SIZE_ASSERT(RCS_MESSAGEHEADER, 8);
RCS_SIZE_ASSERT(RCS_MESSAGE, 288);
RCS_SIZE_ASSERT(RCS_TELEGRAMHEADER_10, 8);
RCS_SIZE_ASSERT(RCS_MESSAGETELEGRAMHEADER_10, 16);
RCS_SIZE_ASSERT(RCS_TELEGRAMHEADERDATA_10, 280);
RCS_SIZE_ASSERT(RCS_MESSAGETELEGRAM_10, 288);

#ifdef __cplusplus
}
#endif

#endif /* CIFEMU_RCS_USER_H_INCLUDED */
