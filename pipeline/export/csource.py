"""A dependency-free C99 calibrator generated from an export's models: one header, one source, libm only.

`generate(models, entry)` writes what a YARP device, a ROS 2 node or a board's firmware wraps: the models of
a graph (`pipeline.calib.parts.GroupModel`, one group or every group fused) as constant tables and one
small interpreter of them, computing what the graph computes (`pipeline.export.graph`), in double:

- per sensor its calibrated wrench from its inputs (the manifest's ``inputs`` order: per sensor fx fy fz N,
  tx ty tz Nm, [temperature degC, [accelerometer m/s^2, gyroscope rad/s]]), less the ``offsets`` row
  (a re-zeroing's, `pipeline.export.offsets`; NULL: zeros);
- ``raw``: the wrench itself; affine, ``play`` and ``arx`` (`pipeline.export.linear`): ``x[:6] + c + A x +
  B (xm - y) / s`` with each operator's output y stepped first (``clip(y' + alpha (xm - y'), xm - r, xm +
  r)``, y' = xm at a fresh start, a NaN); polynomials: ``x[:6] + W phi((x - offset) / scale)``; networks:
  ``x[:6] + A x[:k] + b + mlp(x)`` (normalisation folded into the first layer, output scale into the
  last, `pipeline.export.mlp.stacked_weights`); windowed networks: the play part, plus a network of
  [x[:6], its filters' outputs after the sample, x[6:k]]. The networks run in float32 (as the float32
  graph runs them; weights rounded to float32, inputs by input so that a compiler vectorises them), the
  rest in double.

The state is a caller-owned struct (`ftcal_state_t`, the graph's ``state`` columns in their order, double);
`ftcal_reset` starts every sensor afresh, `ftcal_reset_sensor` one; nothing is allocated. The sensors'
names and serials are constants a caller checks against its robot's boards (`ftcal_sensors`,
`ftcal_serials`: "" where the export recorded none).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pipeline.core.lowpass import operator_columns
from pipeline.export.linear import folded, stackable
from pipeline.export.mlp import stacked_weights
from pipeline.export.trained import WRENCH, GroupModel, IdentityPart, LinearPart, NetworkPart, WindowPart

HEADER, SOURCE = "ftcal_calibrator.h", "ftcal_calibrator.c"
KIND = {"raw": 0, "linear": 1, "poly": 2, "network": 3, "window": 4}
ACTIVATION = {None: 0, "relu": 1, "leaky_relu": 2, "tanh": 3, "elu": 4}

RUNTIME = r"""
static float act(int kind, float alpha, float v) {
    switch (kind) {
    case 1: return v > 0.0f ? v : 0.0f;
    case 2: return v > 0.0f ? v : alpha * v;
    case 3: return tanhf(v);
    case 4: return v > 0.0f ? v : alpha * (expf(v) - 1.0f);
    default: return v;
    }
}

/* out (6) += the network's output on its inputs z (layers[0].cols values), in float32 as the float32 graph */
static void mlp(const ftcal_sensor_t *d, const double *z, double *out) {
    float a[FTCAL_MAX_WIDTH], b[FTCAL_MAX_WIDTH];
    for (int j = 0; j < d->layers[0].cols; ++j) b[j] = (float)z[j];
    const float *h = b;
    for (int l = 0; l < d->n_layers; ++l) {
        const ftcal_layer_t *L = &d->layers[l];
        float *o = (l % 2 == 0) ? a : b;
        /* o = b + sum_j w[:, j] h[j], j in order (weights stored input by input: contiguous, vectorisable) */
        for (int i = 0; i < L->rows; ++i) o[i] = L->b[i];
        for (int j = 0; j < L->cols; ++j) {
            const float hj = h[j], *wj = L->w + j * L->rows;
            for (int i = 0; i < L->rows; ++i) o[i] += wj[i] * hj;
        }
        for (int i = 0; i < L->rows; ++i) o[i] = act(L->act, L->alpha, o[i]);
        h = o;
    }
    for (int i = 0; i < 6; ++i) out[i] += h[i];
}

/* the affine, play and arx parts: the operators stepped on x's wrench, then x[:6] + c + A x + B (xm - y) */
static void linear(const ftcal_sensor_t *d, const double *x, double *y, double *out) {
    for (int m = 0; m < d->n_state; ++m) {
        double xm = x[d->axis[m]], v = y[m];
        if (v != v) v = xm; /* NaN: a fresh start */
        v += d->gain[m] * (xm - v);
        if (v > xm + d->radius[m]) v = xm + d->radius[m];
        if (v < xm - d->radius[m]) v = xm - d->radius[m];
        y[m] = v;
    }
    for (int i = 0; i < 6; ++i) {
        double s = x[i] + d->c[i];
        for (int j = 0; j < d->k; ++j) s += d->a[i * d->k + j] * x[j];
        for (int m = 0; m < d->n_state; ++m) s += d->bm[i * d->n_state + m] * (x[d->axis[m]] - y[m]);
        out[i] = s;
    }
}

static void poly(const ftcal_sensor_t *d, const double *x, double *out) {
    double u[FTCAL_MAX_INPUTS];
    for (int j = 0; j < d->k; ++j) u[j] = (x[j] - d->offset[j]) / d->scale[j];
    for (int i = 0; i < 6; ++i) out[i] = x[i];
    for (int p = 0; p < d->n_terms; ++p) {
        double phi = 1.0;
        for (int j = 0; j < d->k; ++j)
            for (int e = 0; e < d->powers[p * d->k + j]; ++e) phi *= u[j];
        for (int i = 0; i < 6; ++i) out[i] += d->w[i * d->n_terms + p] * phi;
    }
}

static void sensor(const ftcal_sensor_t *d, const double *x, double *y, double *out) {
    double z[FTCAL_MAX_WIDTH];
    int n = 0;
    switch (d->kind) {
    case 0:
        for (int i = 0; i < 6; ++i) out[i] = x[i];
        return;
    case 1: linear(d, x, y, out); return;
    case 2: poly(d, x, out); return;
    case 3:
        for (int i = 0; i < 6; ++i) {
            double s = x[i] + d->c[i];
            for (int j = 0; j < d->k; ++j) s += d->a[i * d->k + j] * x[j];
            out[i] = s;
        }
        mlp(d, x, out);
        return;
    default: /* a windowed network: its play part, and a network of [x[:6], its filters, x[6:k]] */
        linear(d, x, y, out);
        for (int i = 0; i < 6; ++i) z[n++] = x[i];
        for (int f = 0; f < d->n_filters; ++f) z[n++] = y[d->first_filter + f];
        for (int j = 6; j < d->k; ++j) z[n++] = x[j];
        mlp(d, z, out);
        return;
    }
}

void ftcal_reset(ftcal_state_t *state) {
    for (int m = 0; m < FTCAL_STATE_ALLOC; ++m) state->y[m] = NAN;
}

int ftcal_reset_sensor(ftcal_state_t *state, int s) {
    if (s < 0 || s >= FTCAL_N_SENSORS) return -1;
    for (int m = 0; m < SENSORS[s].n_state; ++m) state->y[SENSORS[s].first_state + m] = NAN;
    return 0;
}

int ftcal_sensor_index(const char *name) {
    for (int s = 0; s < FTCAL_N_SENSORS; ++s) {
        const char *a = ftcal_sensors[s], *b = name;
        while (*a && *a == *b) ++a, ++b;
        if (*a == *b) return s;
    }
    return -1;
}

void ftcal_calibrate(ftcal_state_t *state, const float *inputs, const float *offsets, float *outputs) {
    double x[FTCAL_MAX_INPUTS], out[6];
    for (int s = 0; s < FTCAL_N_SENSORS; ++s) {
        const ftcal_sensor_t *d = &SENSORS[s];
        for (int j = 0; j < d->n_inputs; ++j)
            x[j] = (double)inputs[d->first_input + j] - (offsets ? (double)offsets[d->first_input + j] : 0.0);
        sensor(d, x, state->y + d->first_state, out);
        for (int i = 0; i < 6; ++i) outputs[6 * s + i] = (float)out[i];
    }
}

void ftcal_calibrate_rows(ftcal_state_t *state, long n, const float *inputs, const float *offsets,
                          float *outputs) {
    for (long r = 0; r < n; ++r)
        ftcal_calibrate(state, inputs + r * FTCAL_N_INPUTS, offsets, outputs + r * FTCAL_N_OUTPUTS);
}
"""


def _array(name: str, values: Any, ctype: str = "double") -> str:
    flat = np.asarray(values).reshape(-1)
    if not len(flat):
        return ""
    if ctype == "float":  # float32 constants, exact: the value rounded to float32, with all its digits
        body = ",".join(f"{float(np.float32(v))!r}f" for v in flat)
    else:
        body = ",".join(repr(float(v)) if ctype == "double" else str(int(v)) for v in flat)
    return f"static const {ctype} {name}[{len(flat)}] = {{{body}}};\n"


def _layers(prefix: str, part: NetworkPart | WindowPart) -> tuple[str, list[int]]:
    """The C tables of one network's layers (normalisation and output scale folded in), and their widths."""
    code, rows, widths = "", [], []
    for k, (w, b) in enumerate(stacked_weights([part])):
        w, b, layer = w[0], b[0], part.layers[k]
        code += _array(f"{prefix}_w{k}", w.T, "float") + _array(
            f"{prefix}_b{k}", b, "float"
        )  # input by input
        act = ACTIVATION[layer.activation]
        rows.append(
            f"{{{w.shape[0]}, {w.shape[1]}, {act}, {float(layer.alpha)!r}, {prefix}_w{k}, {prefix}_b{k}}}"
        )
        widths += [w.shape[0], w.shape[1]]
    code += f"static const ftcal_layer_t {prefix}_layers[{len(rows)}] = {{{', '.join(rows)}}};\n"
    return code, widths


def _linear_tables(prefix: str, part: LinearPart) -> tuple[str, dict[str, Any]]:
    a, c, b = folded(part)
    radius, gain, scale = operator_columns(part.widths, part.time_constants, part.period)
    m = len(radius)
    fields: dict[str, Any] = {"a": f"{prefix}_a", "c": f"{prefix}_c", "k": a.shape[1], "n_state": m}
    code = _array(f"{prefix}_a", a) + _array(f"{prefix}_c", c)
    if m:
        axis = np.tile(np.arange(WRENCH), m // WRENCH)
        code += _array(f"{prefix}_bm", b / scale[None, :]) + _array(f"{prefix}_axis", axis, "int")
        code += _array(f"{prefix}_radius", np.where(np.isinf(radius), 1e300, radius)) + _array(
            f"{prefix}_gain", gain
        )
        fields |= {k: f"{prefix}_{k}" for k in ("bm", "axis", "radius", "gain")}
    return code, fields


def _sensor_tables(prefix: str, part: Any) -> tuple[str, dict[str, Any], list[int]]:
    """(C tables, descriptor fields, widths used) of one sensor's part."""
    if isinstance(part, IdentityPart):
        return "", {"kind": KIND["raw"]}, []
    if isinstance(part, LinearPart) and stackable(part):
        code, fields = _linear_tables(prefix, part)
        return code, {"kind": KIND["linear"], **fields}, []
    if isinstance(part, LinearPart):
        if part.state_size:
            raise ValueError("a polynomial with memory has no C form")
        code = _array(f"{prefix}_off", part.offset) + _array(f"{prefix}_scl", part.scale)
        code += _array(f"{prefix}_pw", part.powers, "int") + _array(f"{prefix}_w", part.weights)
        fields = {"kind": KIND["poly"], "k": part.powers.shape[1], "n_terms": part.powers.shape[0]}
        fields |= {
            "offset": f"{prefix}_off",
            "scale": f"{prefix}_scl",
            "powers": f"{prefix}_pw",
            "w": f"{prefix}_w",
        }
        return code, fields, []
    if isinstance(part, NetworkPart):
        code, widths = _layers(prefix, part)
        code += _array(f"{prefix}_a", part.affine_weight) + _array(f"{prefix}_c", part.affine_bias)
        fields = {
            "kind": KIND["network"],
            "a": f"{prefix}_a",
            "c": f"{prefix}_c",
            "k": part.affine_weight.shape[1],
        }
        return code, fields | {"n_layers": len(part.layers), "layers": f"{prefix}_layers"}, widths
    if isinstance(part, WindowPart):
        code, fields = _linear_tables(prefix, part.play)
        layers, widths = _layers(prefix, part)
        play = int(part.play.widths.size) if part.play.widths is not None else 0
        filters = WRENCH * len(part.play.time_constants)
        fields |= {"kind": KIND["window"], "first_filter": play, "n_filters": filters}
        return code + layers, fields | {"n_layers": len(part.layers), "layers": f"{prefix}_layers"}, widths
    raise ValueError(f"no C form of {type(part).__name__}")


_FIELDS = (
    "kind", "first_input", "n_inputs", "first_state", "n_state", "k", "a", "c", "bm", "axis", "radius",
    "gain", "n_terms", "powers", "offset", "scale", "w", "n_layers", "layers", "first_filter", "n_filters",
)  # fmt: skip


def generate(models: Sequence[GroupModel], entry: Mapping[str, Any]) -> dict[str, str]:
    """{HEADER: text, SOURCE: text} of the calibrator of `models` side by side (a graph's models, in its
    order) with its manifest `entry` (sensors, serials, inputs)."""
    tables, descriptors, widths = [], [], [1]
    first_input = first_state = 0
    names: list[str] = []
    for model in models:
        for sensor, part in zip(model.sensors, model.parts, strict=True):
            code, fields, used = _sensor_tables(f"s{len(names)}", part)
            fields |= {"first_input": first_input, "n_inputs": model.n_inputs, "first_state": first_state}
            fields.setdefault("n_state", 0)
            tables.append(code)
            descriptors.append("{" + ", ".join(f".{f} = {fields[f]}" for f in _FIELDS if f in fields) + "}")
            widths += used
            first_input += model.n_inputs
            first_state += int(fields["n_state"])
            names.append(sensor)
    serials = entry.get("serials") or {}
    header = _header(names, [serials.get(s) or "" for s in names], first_input, first_state, entry)
    source = "\n".join(
        [
            f'#include "{HEADER}"',
            "#include <math.h>",
            "",
            f"#define FTCAL_MAX_WIDTH {max(widths) + 6}",
            f"#define FTCAL_MAX_INPUTS {max(m.n_inputs for m in models)}",
            f"#define FTCAL_STATE_ALLOC {max(first_state, 1)}",
            "",
            "const char *const ftcal_sensors[FTCAL_N_SENSORS] = {"
            + ", ".join(f'"{s}"' for s in names)
            + "};",
            "const char *const ftcal_serials[FTCAL_N_SENSORS] = {"
            + ", ".join(f'"{serials.get(s) or ""}"' for s in names)
            + "};",
            "",
            *tables,
            f"static const ftcal_sensor_t SENSORS[{len(names)}] = {{\n    "
            + ",\n    ".join(descriptors)
            + "\n};",
            RUNTIME,
        ]
    )
    return {HEADER: header, SOURCE: source}


def _header(
    names: list[str], serials: list[str], n_inputs: int, n_state: int, entry: Mapping[str, Any]
) -> str:
    inputs = "\n".join(
        f" *   {c['index']:3d} {c['sensor']} {c['field']} [{c['unit']}]" for c in entry.get("inputs") or []
    )
    return f"""/* ftcal calibrator: generated by `ftcal export` from the export beside it; C99, libm only.
 *
 * Sensors (outputs[6 s .. 6 s + 5] = fx fy fz N, tx ty tz Nm of sensor s, sensor frame): {", ".join(names)}
 * Inputs, one row per sample (offsets: the same columns, subtracted first; NULL for none):
{inputs}
 */
#ifndef FTCAL_CALIBRATOR_H
#define FTCAL_CALIBRATOR_H

#define FTCAL_N_SENSORS {len(names)}
#define FTCAL_N_INPUTS {n_inputs}
#define FTCAL_N_OUTPUTS {6 * len(names)}
#define FTCAL_STATE_SIZE {n_state}

typedef struct {{ int rows, cols, act; float alpha; const float *w, *b; }} ftcal_layer_t;
typedef struct {{
    int kind, first_input, n_inputs, first_state, n_state, k;
    const double *a, *c, *bm;
    const int *axis;
    const double *radius, *gain;
    int n_terms;
    const int *powers;
    const double *offset, *scale, *w;
    int n_layers;
    const ftcal_layer_t *layers;
    int first_filter, n_filters;
}} ftcal_sensor_t;

/* the play operators' and filters' outputs (the graph's state columns), owned by the caller */
typedef struct {{ double y[{max(n_state, 1)}]; }} ftcal_state_t;

extern const char *const ftcal_sensors[FTCAL_N_SENSORS]; /* URDF sensor names, in output order */
extern const char *const ftcal_serials[FTCAL_N_SENSORS]; /* the boards the calibration is for ("": unknown) */

void ftcal_reset(ftcal_state_t *state);                 /* every sensor starts afresh at its next sample */
int ftcal_reset_sensor(ftcal_state_t *state, int sensor); /* one sensor; -1 if no such sensor */
int ftcal_sensor_index(const char *name);               /* -1 if not a sensor of this calibrator */
/* one sample of every sensor: inputs[FTCAL_N_INPUTS] -> outputs[FTCAL_N_OUTPUTS] */
void ftcal_calibrate(ftcal_state_t *state, const float *inputs, const float *offsets, float *outputs);
/* n consecutive samples, row after row */
void ftcal_calibrate_rows(ftcal_state_t *state, long n, const float *inputs, const float *offsets,
                          float *outputs);

#endif
"""
