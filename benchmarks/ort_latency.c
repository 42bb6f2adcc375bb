/* Single-sample latency of an ONNX graph through onnxruntime's C API, as a robot's C/C++ control loop
 * calls it: one session on one thread, input and output tensors created once over the loop's own
 * buffers, then per cycle: write one input row, Run, (read the output row).
 *
 * Built and run by benchmarks/infer_speed.py (cc -O2 ort_latency.c -ldl). It loads the onnxruntime
 * library of the Python wheel (capi/libonnxruntime.so.*) with dlopen, so no header or link step is
 * needed: the few OrtApi functions used are called through their slots in the OrtApi table (their
 * indices are part of onnxruntime's stable C ABI: members are only ever appended).
 *
 *   ort_latency LIB MODEL INPUT OUTPUT N_IN N_OUT ROWS_FILE N_ROWS CALLS WARMUP [STATE STATE_OUT N_STATE]
 *
 * A graph with memory (`pipeline.export.linear`: the play models) has a state input and output of N_STATE
 * float32: the loop carries it as a robot's loop must, the output of one call the input of the next, in two
 * buffers it swaps (one tensor over each, created once; the state starts at NaN, a fresh start).
 *
 * ROWS_FILE: N_ROWS rows of N_IN float32 (native byte order), cycled through. Prints one JSON line:
 * {"version": "...", "p50_us": ..., "p99_us": ..., "checksum": ...} (checksum: the sum of the first output
 * of every call, warm-up included, for a test to compare with the Python API). Exit 1 with a message on
 * error.
 */
#include <dlfcn.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "latency.h"

typedef void *Status; /* OrtStatus*, NULL on success */
typedef struct {
  const void **(*GetApi)(uint32_t version);
  const char *(*GetVersionString)(void);
} ApiBase;

/* Slots of the OrtApi table (onnxruntime_c_api.h, API version 1 onwards). */
enum {
  GET_ERROR_MESSAGE = 2,
  CREATE_ENV = 3,
  CREATE_SESSION = 7,
  RUN = 9,
  CREATE_SESSION_OPTIONS = 10,
  SET_GRAPH_OPTIMIZATION_LEVEL = 23,
  SET_INTRA_OP_THREADS = 24,
  SET_INTER_OP_THREADS = 25,
  CREATE_TENSOR_WITH_DATA = 49,
  CREATE_CPU_MEMORY_INFO = 69,
};
enum { LOG_WARNING = 2, ENABLE_ALL = 99, FLOAT = 1, ARENA_ALLOCATOR = 1, MEM_DEFAULT = 0 };

static const void **api;
#define FN(slot, type) ((type)api[slot])

static void check(Status status, const char *what) {
  if (status) {
    fprintf(stderr, "onnxruntime %s: %s\n", what, FN(GET_ERROR_MESSAGE, const char *(*)(Status))(status));
    exit(1);
  }
}


int main(int argc, char **argv) {
  if (argc != 11 && argc != 14) {
    fprintf(stderr, "usage: %s LIB MODEL INPUT OUTPUT N_IN N_OUT ROWS_FILE N_ROWS CALLS WARMUP "
            "[STATE STATE_OUT N_STATE]\n", argv[0]);
    return 1;
  }
  int n_state = argc == 14 ? atoi(argv[13]) : 0;
  const char *input_name = argv[3], *output_name = argv[4];
  int n_in = atoi(argv[5]), n_out = atoi(argv[6]), n_rows = atoi(argv[8]);
  int calls = atoi(argv[9]), warmup = atoi(argv[10]);
  void *lib = dlopen(argv[1], RTLD_NOW);
  if (!lib) {
    fprintf(stderr, "cannot load onnxruntime: %s\n", dlerror());
    return 1;
  }
  const ApiBase *(*get_base)(void) = (const ApiBase *(*)(void))dlsym(lib, "OrtGetApiBase");
  if (!get_base || !(api = get_base()->GetApi(1))) {
    fprintf(stderr, "%s: no OrtGetApiBase / API version 1\n", argv[1]);
    return 1;
  }
  float *rows = malloc(sizeof(float) * n_in * n_rows), *x = calloc(n_in, sizeof(float));
  float *y = calloc(n_out, sizeof(float));
  float *states[2] = {malloc(sizeof(float) * (n_state + 1)), malloc(sizeof(float) * (n_state + 1))};
  for (int i = 0; i < n_state; i++) states[0][i] = states[1][i] = NAN;
  double *times = malloc(sizeof(double) * calls);
  FILE *f = fopen(argv[7], "rb");
  if (!f || fread(rows, sizeof(float) * n_in, n_rows, f) != (size_t)n_rows) {
    fprintf(stderr, "%s: cannot read %d rows of %d float32\n", argv[7], n_rows, n_in);
    return 1;
  }
  fclose(f);

  void *env, *options, *session, *memory, *input, *output;
  check(FN(CREATE_ENV, Status(*)(int, const char *, void **))(LOG_WARNING, "ftcal", &env), "CreateEnv");
  check(FN(CREATE_SESSION_OPTIONS, Status(*)(void **))(&options), "CreateSessionOptions");
  check(FN(SET_GRAPH_OPTIMIZATION_LEVEL, Status(*)(void *, int))(options, ENABLE_ALL), "optimization level");
  check(FN(SET_INTRA_OP_THREADS, Status(*)(void *, int))(options, 1), "SetIntraOpNumThreads");
  check(FN(SET_INTER_OP_THREADS, Status(*)(void *, int))(options, 1), "SetInterOpNumThreads");
  check(FN(CREATE_SESSION, Status(*)(void *, const char *, void *, void **))(env, argv[2], options, &session),
        "CreateSession");
  check(FN(CREATE_CPU_MEMORY_INFO, Status(*)(int, int, void **))(ARENA_ALLOCATOR, MEM_DEFAULT, &memory),
        "CreateCpuMemoryInfo");
  typedef Status (*CreateTensor)(void *, void *, size_t, const int64_t *, size_t, int, void **);
  int64_t x_shape[2] = {1, n_in}, y_shape[2] = {1, n_out};
  check(FN(CREATE_TENSOR_WITH_DATA, CreateTensor)(memory, x, sizeof(float) * n_in, x_shape, 2, FLOAT, &input),
        "input tensor");
  check(FN(CREATE_TENSOR_WITH_DATA, CreateTensor)(memory, y, sizeof(float) * n_out, y_shape, 2, FLOAT, &output),
        "output tensor");
  void *state[2] = {NULL, NULL};
  int64_t s_shape[1] = {n_state};
  for (int b = 0; b < 2 && n_state; b++)
    check(FN(CREATE_TENSOR_WITH_DATA, CreateTensor)(memory, states[b], sizeof(float) * n_state, s_shape, 1, FLOAT,
                                                    &state[b]),
          "state tensor");
  typedef Status (*Run)(void *, void *, const char *const *, void *const *, size_t, const char *const *, size_t,
                        void **);
  Run run = FN(RUN, Run);
  const char *in_names[2] = {input_name, n_state ? argv[11] : NULL};
  const char *out_names[2] = {output_name, n_state ? argv[12] : NULL};
  size_t n_io = n_state ? 2 : 1;

  double checksum = 0.0;
  for (int k = -warmup; k < calls; k++) {
    const float *row = rows + (size_t)((k + warmup) % n_rows) * n_in;
    for (int i = 0; i < n_in; i++) x[i] = row[i];
    int now = (k + warmup) & 1; /* the state of the call before is in buffer `now`, this call's goes to the other */
    void *inputs[2] = {input, state[now]}, *outputs[2] = {output, state[1 - now]};
    double start = now_us();
    check(run(session, NULL, in_names, inputs, n_io, out_names, n_io, outputs), "Run");
    double stop = now_us();
    if (k >= 0) times[k] = stop - start;
    checksum += y[0];
  }
  qsort(times, calls, sizeof(double), by_value);
  printf("{\"version\": \"%s\", \"p50_us\": %.3f, \"p99_us\": %.3f, \"checksum\": %.17g}\n",
         get_base()->GetVersionString(), times[calls / 2], times[(size_t)calls * 99 / 100], checksum);
  return 0;
}
