/*
 * driver.h - libcif's state shared by its source files (not installed).
 */
#ifndef CIFEMU_DRIVER_H
#define CIFEMU_DRIVER_H

#include <limits.h>

#include "bell.h"
#include "chanlock.h"
#include "cif_user.h"

#define CIFEMU_HIDDEN __attribute__((visibility("hidden")))

typedef struct cifemu_counters {
  unsigned int open, close, read, write, irq, io;
  unsigned char last_function;
} cifemu_counters;

typedef struct cifemu_board {
  unsigned short number;
  unsigned char *mm; /* the map; flag bytes are read through flag_get (volatile) */
  cifemu_bell bell;
  /* put and get: thread locks only, inside the transaction lock (chanlock.h) */
  cifemu_chanlock put_lock, get_lock, io_lock;
  cifemu_counters *counters;
  /* [ours] The spin's back-off (wait_for_ringing), shared by the board's threads (a race
     costs one watch more or less): watches in a row that the answer outlasted, and the
     waits left that sleep on the bell at once. */
  unsigned spin_misses, spin_skip;
  /* The board's transaction lock as this process holds it across calls [ours]: from a
     DevPutMessage until its answer is read, so that another host's transaction (a Python
     host's Board.transact, another C host) never takes this host's answers, nor this
     host theirs; its ledger names the answers of hosts that died or gave up waiting. */
  cifemu_txn txn;
  char firmware_lock[PATH_MAX + 32]; /* board<N>.firmware.lock, whatever the driver does */
  /* [ours] Guarded by the board table's lock: the calls inside on this board, and whether
     DevExitBoard (or the last DevCloseDriver) closed it meanwhile. A closed board leaves
     the table at once; the last call inside unmaps and frees it. */
  unsigned users;
  int closing;
  struct cifemu_board *next_closing; /* the closed boards calls are still inside */
} cifemu_board;

/* A call enters the initialised board: NULL with *rc saying why (-34; -32 also for a
   board DevExitBoard closed), else the board (*rc 0), mapped until cifemu_board_leave. */
CIFEMU_HIDDEN cifemu_board *cifemu_board_enter(unsigned short number, short *rc);
/* As cifemu_board_enter, and the card must be READY (-11; the board is left then). */
CIFEMU_HIDDEN cifemu_board *cifemu_ready_board(unsigned short number, short *rc);
/* The call is done with the board: the last call inside a closed board unmaps it. */
CIFEMU_HIDDEN void cifemu_board_leave(cifemu_board *b);

#endif
