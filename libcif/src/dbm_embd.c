/*
 * dbm_embd.c - see dbm_embd.h. The container is that of docs/dbm.md section 1 (and
 * dbm_tools/container.py): root block of 208 words, then per table a key index (keyed
 * tables), a directory, a descriptor and the record blocks; every pointer a word index.
 * Every pointer and length is checked against the data area before it is followed, so a
 * malformed file gives a code and never a read outside the buffer.
 */
#include "dbm_embd.h"

#include <string.h>

#define CIF_API __attribute__((visibility("default")))

#define FILE_HEADER_SIZE 44
#define ROOT_WORDS 208
#define FIRST_TABLE 8
#define BLOCK_HEADER 12
#define BLOCK_RECORD 0
#define BLOCK_DIRECTORY 1
#define BLOCK_DESCRIPTOR 4
#define DESCRIPTOR_SIZE (14 + 18)
#define DESCRIPTOR_POSITION 6

static const unsigned char DBM_FILE_MAGIC[10] = {'D', 'B', 'M', 'F', 'I', 'L', 'E', ' ', ' ', 0};

static const unsigned char *area;   /* the data area of the file dbm_init took */
static unsigned long area_size;     /* its bytes */
static unsigned tables;             /* root word w3 */

static unsigned word(unsigned long byte_offset) {
  return area[byte_offset] | (unsigned)area[byte_offset + 1] << 8;
}

/* The payload of the block at word `at`, when it is one of `kind`; NULL otherwise. */
static const unsigned char *block(unsigned at, unsigned kind, unsigned long *payload_size) {
  unsigned long offset = 2UL * at, length, pad;
  if (at < ROOT_WORDS || offset + BLOCK_HEADER > area_size) return NULL;
  if (word(offset) != kind) return NULL;
  pad = word(offset + 8);
  length = word(offset + 10);
  if (pad > 1 || length < BLOCK_HEADER + pad || offset + length > area_size) return NULL;
  *payload_size = length - BLOCK_HEADER - pad;
  return area + offset + BLOCK_HEADER;
}

/* The descriptor and directory of the table in root slot `handle`. */
static int table(unsigned handle, const unsigned char **directory, unsigned long *slots,
                 const unsigned char **descriptor) {
  unsigned long size;
  if (area == NULL || handle < FIRST_TABLE || handle % 2 ||
      handle >= FIRST_TABLE + 2 * tables)
    return 0;
  *directory = block(word(2UL * handle), BLOCK_DIRECTORY, &size);
  if (*directory == NULL || size < 2) return 0;
  *slots = size / 2;
  *descriptor = block((*directory)[0] | (unsigned)(*directory)[1] << 8, BLOCK_DESCRIPTOR, &size);
  return *descriptor != NULL && size == DESCRIPTOR_SIZE;
}

CIF_API short dbm_init_ex(const void *ptDbmFile, unsigned long ulSize) {
  const unsigned char *file = (const unsigned char *)ptDbmFile;
  unsigned long size, sum = 0, i;
  area = NULL;
  if (file == NULL) return DBM_NO_DAT;
  if (ulSize >= sizeof DBM_FILE_MAGIC && memcmp(file, DBM_FILE_MAGIC, sizeof DBM_FILE_MAGIC) == 0) {
    if (ulSize < FILE_HEADER_SIZE) return DBM_NO_DAT;
    size = file[38] | (unsigned long)file[39] << 8;
    if (size > ulSize - FILE_HEADER_SIZE) return DBM_NO_DAT;
    file += FILE_HEADER_SIZE;
  } else {
    if (ulSize < 2 * ROOT_WORDS) return DBM_NO_DAT;
    size = 2UL * (file[10] | (unsigned long)file[11] << 8); /* w5 */
    if (size > ulSize) return DBM_NO_DAT;
  }
  if (size < 2 * ROOT_WORDS || size % 2) return DBM_NO_DAT;
  area = file;
  area_size = size;
  for (i = 2; i < size; i += 2) sum += word(i);
  if ((sum & 0xFFFF) != word(0) || word(10) != word(12) || 2UL * word(10) != size) {
    area = NULL;
    return DBM_NO_DAT; /* the checksum w0 or the root's length words do not fit */
  }
  tables = word(6);
  if (tables > DBM_MAX_TAB) {
    area = NULL;
    return DBM_DAT_DIR_FULL;
  }
  return DBM_OK;
}

CIF_API short dbm_init(void *ptDbmFile) {
  const unsigned char *file = (const unsigned char *)ptDbmFile;
  unsigned long size;
  if (file == NULL) return DBM_NO_DAT;
  /* The file says how long it is: the header's length word, or a bare area's w5. */
  if (memcmp(file, DBM_FILE_MAGIC, sizeof DBM_FILE_MAGIC) == 0)
    size = FILE_HEADER_SIZE + (file[38] | (unsigned long)file[39] << 8);
  else
    size = 2UL * (file[10] | (unsigned long)file[11] << 8);
  return dbm_init_ex(file, size);
}

CIF_API short dbm_get_num(unsigned char *pszName, unsigned char *pbHandle) {
  const unsigned char *directory, *descriptor;
  unsigned long slots;
  unsigned handle;
  if (pszName == NULL || pbHandle == NULL || area == NULL) return DBM_NO_DAT;
  for (handle = FIRST_TABLE; handle < FIRST_TABLE + 2 * tables; handle += 2) {
    if (!table(handle, &directory, &slots, &descriptor)) continue;
    /* the name is NUL-padded in 18 bytes; compare up to and including its NUL */
    if (strncmp((const char *)descriptor + 14, (const char *)pszName, 18) == 0 &&
        memchr(descriptor + 14, 0, 18) != NULL) {
      *pbHandle = (unsigned char)handle;
      return DBM_OK;
    }
  }
  return DBM_NO_DAT;
}

CIF_API short dbm_get_num_of_set(unsigned char bHandle, unsigned short *pusNumberOfSets) {
  const unsigned char *directory, *descriptor;
  unsigned long slots;
  if (pusNumberOfSets == NULL || !table(bHandle, &directory, &slots, &descriptor))
    return DBM_NO_DAT;
  *pusNumberOfSets = (unsigned short)(descriptor[2] | descriptor[3] << 8); /* f1 */
  return DBM_OK;
}

CIF_API short dbm_fast_read(unsigned char bHandle, unsigned short usSetNumber,
                            unsigned short usMaximumLength, void *pvDestinationPointer,
                            unsigned short *pusRealLength) {
  const unsigned char *directory, *descriptor, *payload;
  unsigned long slots, size;
  unsigned count, at;
  if (!table(bHandle, &directory, &slots, &descriptor)) return DBM_NO_DAT;
  count = descriptor[2] | (unsigned)descriptor[3] << 8;
  if (usSetNumber == 0 || usSetNumber > count || usSetNumber >= slots) return DBM_NO_SET;
  at = directory[2 * usSetNumber] | (unsigned)directory[2 * usSetNumber + 1] << 8;
  payload = at ? block(at, BLOCK_RECORD, &size) : NULL;
  if (payload == NULL || size > 0xFFFF) return DBM_SET_DEL;
  if (pusRealLength != NULL) *pusRealLength = (unsigned short)size;
  if (size > usMaximumLength) return DBM_NOT_ENOUGH_FREESPACE;
  if (size > 0 && pvDestinationPointer == NULL) return DBM_NOT_ENOUGH_FREESPACE;
  if (size > 0) memcpy(pvDestinationPointer, payload, size);
  return DBM_OK;
}
