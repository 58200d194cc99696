/*
 * spin_backoff.c - a C host whose answers outlast its watch of the flags stops watching
 * (libcif/src/cif_api.c, spin; tests/test_mailbox_spin.py).
 *
 * DevGetMessage with a 1 ms time-out, CALLS times, on a card that sends nothing. This
 * program's clock_gettime comes before libc's for libcif too, and counts: a call that
 * watches the flags reads the clock at every look, hundreds of times in its 100 us, one
 * that sleeps on the bell at once a few times. Prints "rc readings" per call.
 *
 * Usage: spin_backoff CALLS   (CIF_DPM_DIR names the card's directory)
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "cif_user.h"

typedef int (*clock_fn)(clockid_t, struct timespec *);

static unsigned long readings;

int clock_gettime(clockid_t id, struct timespec *ts) {
  static clock_fn real;
  if (real == NULL) *(void **)&real = dlsym(RTLD_NEXT, "clock_gettime");
  __atomic_fetch_add(&readings, 1UL, __ATOMIC_RELAXED);
  return real(id, ts);
}

int main(int argc, char **argv) {
  MSG_STRUC msg;
  int i, calls = argc == 2 ? atoi(argv[1]) : 0;
  short rc;
  if (calls <= 0) {
    fprintf(stderr, "usage: spin_backoff CALLS\n");
    return 2;
  }
  if ((rc = DevOpenDriver()) != DRV_NO_ERROR || (rc = DevInitBoard(0)) != DRV_NO_ERROR) {
    fprintf(stderr, "open: %d\n", rc);
    return 1;
  }
  for (i = 0; i < calls; i++) {
    unsigned long before = __atomic_load_n(&readings, __ATOMIC_RELAXED);
    rc = DevGetMessage(0, sizeof msg, &msg, 1);
    printf("%d %lu\n", rc, __atomic_load_n(&readings, __ATOMIC_RELAXED) - before);
  }
  DevExitBoard(0);
  DevCloseDriver();
  return 0;
}
