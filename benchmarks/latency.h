/* What the latency loops (benchmarks/ort_latency.c, benchmarks/c_latency.c) share: the clock and the sort. */
#ifndef FTCAL_BENCHMARK_LATENCY_H
#define FTCAL_BENCHMARK_LATENCY_H
#include <time.h>

static int by_value(const void *a, const void *b) {
  double d = *(const double *)a - *(const double *)b;
  return (d > 0) - (d < 0);
}

static double now_us(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec * 1e6 + t.tv_nsec / 1e3;
}
#endif
