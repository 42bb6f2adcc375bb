/* Single-sample latency of ftcal's generated C calibrator (`ftcal export`: exported/c/ftcal_calibrator.c),
 * as a robot's control loop calls it: one state struct, one call per cycle for all the sensors, the
 * re-zeroing's offsets row bound once (zeros here).
 *
 * Built and run by benchmarks/infer_speed.py:
 *   cc -O3 -std=c99 -I DIR c_latency.c DIR/ftcal_calibrator.c -lm
 *   c_latency ROWS_FILE N_ROWS CALLS WARMUP
 *
 * ROWS_FILE: N_ROWS rows of FTCAL_N_INPUTS float32 (native byte order), cycled through, the same rows as
 * benchmarks/ort_latency.c's. Prints one JSON line {"p50_us": ..., "p99_us": ..., "checksum": ...}
 * (checksum: the sum of the first output of every call, warm-up included). Exit 1 with a message on error.
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "latency.h"

#include "ftcal_calibrator.h" /* the calibrator's folder on the include path (-I) */


int main(int argc, char **argv) {
  if (argc != 5) {
    fprintf(stderr, "usage: %s ROWS_FILE N_ROWS CALLS WARMUP\n", argv[0]);
    return 1;
  }
  int n_rows = atoi(argv[2]), calls = atoi(argv[3]), warmup = atoi(argv[4]);
  float *rows = malloc(sizeof(float) * FTCAL_N_INPUTS * (size_t)n_rows);
  double *times = malloc(sizeof(double) * (size_t)calls);
  FILE *f = fopen(argv[1], "rb");
  if (!rows || !times || !f || fread(rows, sizeof(float) * FTCAL_N_INPUTS, n_rows, f) != (size_t)n_rows) {
    fprintf(stderr, "%s: cannot read %d rows of %d float32\n", argv[1], n_rows, FTCAL_N_INPUTS);
    return 1;
  }
  fclose(f);
  static float x[FTCAL_N_INPUTS], offsets[FTCAL_N_INPUTS], y[FTCAL_N_OUTPUTS];
  static ftcal_state_t state;
  ftcal_reset(&state);
  double checksum = 0.0;
  for (int k = -warmup; k < calls; k++) {
    const float *row = rows + (size_t)((k + warmup) % n_rows) * FTCAL_N_INPUTS;
    for (int i = 0; i < FTCAL_N_INPUTS; i++) x[i] = row[i];
    double start = now_us();
    ftcal_calibrate(&state, x, offsets, y);
    double stop = now_us();
    if (k >= 0) times[k] = stop - start;
    checksum += y[0];
  }
  qsort(times, calls, sizeof(double), by_value);
  printf("{\"p50_us\": %.3f, \"p99_us\": %.3f, \"checksum\": %.17g}\n", times[calls / 2],
         times[(size_t)calls * 99 / 100], checksum);
  return 0;
}
