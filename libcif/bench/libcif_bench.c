/*
 * libcif_bench.c - the timing loops of bench/libcif.py, in C, so the figures are libcif's
 * and not those of a Python caller.
 *
 *   libcif_bench mailbox COUNT WARMUP
 *       DevPutMessage + DevGetMessage of a COM_Shared_Memory read (16 bytes out, 24 back)
 *   libcif_bench exchange COUNT WARMUP BMODE
 *       warm start with bMode BMODE, then DevExchangeIO of 32 bytes out and 32 in
 *
 * Prints one JSON object: count, elapsed_ns of a loop of COUNT calls timed as a whole,
 * failures, the warm-up's return codes, and latencies_ns of up to 20000 calls timed
 * one by one (a separate loop, so reading the clock does not lower the rate).
 * $CIF_DPM_DIR names the card's image directory.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cif_user.h"

#define MAX_SAMPLES 20000
#define TIMEOUT_MS 1000L
#define BAD_ANSWER -1000

static long long now_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static MSG_STRUC request, answer;
static unsigned char outputs[32], inputs[32];
static unsigned char sequence;

static int round_trip(void) {
  short rc;
  request.nr = ++sequence;
  rc = DevPutMessage(0, &request, TIMEOUT_MS);
  if (rc != DRV_NO_ERROR) return rc;
  rc = DevGetMessage(0, sizeof answer, &answer, TIMEOUT_MS);
  if (rc != DRV_NO_ERROR) return rc;
  return answer.nr == sequence && answer.f == 0 && answer.ln == 16 ? 0 : BAD_ANSWER;
}

static int exchange(void) {
  short rc = DevExchangeIO(0, 0, sizeof outputs, outputs, 0, sizeof inputs, inputs, TIMEOUT_MS);
  return rc == DRV_DEV_NO_COM_FLAG ? 0 : rc; /* no bus configured: exchanged, COM clear */
}

int main(int argc, char **argv) {
  static long long samples[MAX_SAMPLES];
  int (*step)(void);
  long count, warmup, i, failures = 0, n_samples;
  int codes[2][16], n_codes = 0, k;
  long long start, elapsed;
  short rc;
  if (argc < 4) {
    fprintf(stderr, "usage: libcif_bench mailbox|exchange COUNT WARMUP [BMODE]\n");
    return 2;
  }
  count = atol(argv[2]);
  warmup = atol(argv[3]);
  if ((rc = DevOpenDriver()) != 0 || (rc = DevInitBoard(0)) != 0) {
    fprintf(stderr, "libcif_bench: open: %d\n", rc);
    return 1;
  }
  if (strcmp(argv[1], "mailbox") == 0) {
    static const unsigned char telegram[8] = {0, 1, 0, 0, 0, 8, 5, 1};
    request.rx = 2;
    request.tx = 16;
    request.b = 17;
    request.ln = sizeof telegram;
    memcpy(request.data, telegram, sizeof telegram);
    step = round_trip;
  } else if (strcmp(argv[1], "exchange") == 0 && argc == 5) {
    unsigned char parameter[3] = {(unsigned char)atoi(argv[4]), 0, 0};
    for (i = 0; i < (long)sizeof outputs; i++) outputs[i] = (unsigned char)i;
    if ((rc = DevPutTaskParameter(0, 2, sizeof parameter, parameter)) != 0 ||
        (rc = DevReset(0, WARMSTART, 5000L)) != 0) {
      fprintf(stderr, "libcif_bench: warm start: %d\n", rc);
      return 1;
    }
    step = exchange;
  } else {
    fprintf(stderr, "libcif_bench: unknown benchmark %s\n", argv[1]);
    return 2;
  }
  for (i = 0; i < warmup; i++) {
    int code = step();
    for (k = 0; k < n_codes && codes[k][0] != code; k++) {
    }
    if (k == n_codes && n_codes < 16) codes[n_codes++][0] = code, codes[k][1] = 0;
    if (k < 16) codes[k][1]++;
  }
  n_samples = count < MAX_SAMPLES ? count : MAX_SAMPLES;
  for (i = 0; i < n_samples; i++) {
    start = now_ns();
    if (step() != 0) failures++;
    samples[i] = now_ns() - start;
  }
  start = now_ns();
  for (i = 0; i < count; i++)
    if (step() != 0) failures++;
  elapsed = now_ns() - start;
  printf("{\"count\": %ld, \"elapsed_ns\": %lld, \"failures\": %ld, \"warmup_codes\": {", count,
         elapsed, failures);
  for (k = 0; k < n_codes; k++) printf("%s\"%d\": %d", k ? ", " : "", codes[k][0], codes[k][1]);
  printf("}, \"latencies_ns\": [");
  for (i = 0; i < n_samples; i++) printf("%s%lld", i ? ", " : "", samples[i]);
  printf("]}\n");
  DevExitBoard(0);
  DevCloseDriver();
  return 0;
}
