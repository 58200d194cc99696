/*
 * dbm_embd.h - reading a SyCon DBM configuration file in an embedded host program
 * (seed manual 6.5), as part of cifemu's libcif.
 *
 * dbm_init() takes the file as it sits in memory (the 44-byte file header and the data
 * area, or a bare data area as the card stores it); the other functions find a table by
 * name, count its data sets and copy one out. One file at a time, as on the card.
 *
 * Not thread-safe: the functions share the one file dbm_init() was given.
 */
#ifndef CIFEMU_DBM_EMBD_H_INCLUDED
#define CIFEMU_DBM_EMBD_H_INCLUDED

#ifdef __cplusplus
extern "C" {
#endif

#define DBM_OK                   0 /* no error */
#define DBM_NO_DAT               1 /* table name not found; handle not valid */
#define DBM_NO_SET               2 /* set number out of range */
#define DBM_DAT_DIR_FULL         3 /* more tables than DBM_MAX_TAB */
#define DBM_NOT_ENOUGH_FREESPACE 4 /* the destination buffer is too small */
#define DBM_SET_DEL              5 /* the data set is not available */

#define DBM_MAX_TAB              100 /* table slots of a DBM root block */

/* Takes the file at ptDbmFile; its length is the one its header states (for a bare data
   area: root word w5). [ours] A buffer that is not a well-formed DBM gives DBM_NO_DAT. */
short dbm_init(void *ptDbmFile);
/* [ours] dbm_init for a buffer of ulSize bytes: nothing beyond them is ever read. */
short dbm_init_ex(const void *ptDbmFile, unsigned long ulSize);
short dbm_get_num(unsigned char *pszName, unsigned char *pbHandle);
short dbm_get_num_of_set(unsigned char bHandle, unsigned short *pusNumberOfSets);
/* usSetNumber counts from 1. *pusRealLength is the set's length, also when it does not fit. */
short dbm_fast_read(unsigned char bHandle, unsigned short usSetNumber,
                    unsigned short usMaximumLength, void *pvDestinationPointer,
                    unsigned short *pusRealLength);

#ifdef __cplusplus
}
#endif

#endif /* CIFEMU_DBM_EMBD_H_INCLUDED */
