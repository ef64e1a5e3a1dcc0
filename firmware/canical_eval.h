/*
 * canical_eval: run a canical coefficient set on the sensor's own MCU.
 *
 * One portable C99 library for every set: a set arrives at run time as the bytes of a
 * coefficient bank (the set's canonical JSON, object 0x2210-0x2215 sub 1) and its declared
 * CRC32 (sub 2). ce_load() validates those bytes exactly as the device must and turns them
 * into a ce_set; ce_eval() corrects one sample with it.
 *
 * - No heap, no recursion, no libm: the per-sample path uses float32 add, subtract,
 *   multiply, divide and compare only (a Cortex-M4F's FPU does all of them in hardware);
 *   exp() for the warm-up, slope, lag and derivative terms is computed here with those operations.
 *   ce_load() parses numbers in double precision (software floating point on a
 *   single-precision FPU: load time only, never per sample).
 * - Bounded work per sample: at most CE_MAX_TERMS terms, CE_MAX_SEGMENTS segments and
 *   CE_MAX_COEFFS coefficients per polynomial; the forward polynomial's Newton inversion
 *   stops after CE_NEWTON_MAX_ITER steps; a spline term is a binary search over at most
 *   CE_MAX_SPLINE_KNOTS knots (6 steps for 64) and one cubic.
 * - ce_load() never reads outside [content, content + length) and writes only *set.
 * - The build-time limits (CE_MAX_*) are checked here with #error: a limit that does not fit the
 *   field counting it fails the build, not a set at run time.
 * - Internal invariants are checked with CE_ASSERT in canical_eval.c: assert() in a hosted build,
 *   nothing with NDEBUG or in a freestanding build (define CE_ASSERT to use your own).
 *
 * MIT licence, like the rest of canical.
 */
#ifndef CANICAL_EVAL_H
#define CANICAL_EVAL_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Device limits: sets beyond them are refused with CE_ERR_LIMIT (raise them if RAM allows). */
#ifndef CE_MAX_SEGMENTS
#define CE_MAX_SEGMENTS 16 /* segments of a piecewise model */
#endif
#ifndef CE_MAX_COEFFS
#define CE_MAX_COEFFS 10 /* coefficients per polynomial (order 9) */
#endif
#ifndef CE_MAX_TERMS
#define CE_MAX_TERMS 16 /* effect terms of a set */
#endif
#ifndef CE_MAX_INPUTS
#define CE_MAX_INPUTS 8 /* run-time channels a device offers */
#endif
#ifndef CE_MAX_DEPTH
#define CE_MAX_DEPTH 16 /* JSON nesting (the "fit" statistics may nest) */
#endif
#ifndef CE_MAX_SPLINE_KNOTS
#define CE_MAX_SPLINE_KNOTS 64 /* knots of one spline term (canical.sets.term_kinds.MAX_SPLINE_KNOTS) */
#endif
#ifndef CE_MAX_SPLINES
#define CE_MAX_SPLINES 4 /* spline terms of a set (canical.sets.admission.MAX_SPLINE_TERMS) */
#endif
#define CE_MIN_TAU_S 1e-6 /* a term's time constant, s, at least (canical.sets.terms.MIN_TAU_S) */
#define CE_MAX_TAU_S 1e9 /* and at most (canical.sets.terms.MAX_TAU_S) */
#define CE_NAME_MAX 24 /* longest channel name, bytes */
#define CE_NEWTON_MAX_ITER 40 /* Newton steps of the forward polynomial's inversion, at most */

/* Each limit must fit the uint8_t that counts it in ce_set, ce_fixed and ce_device, and be at
 * least 1 (arrays are sized by it). */
#if CE_MAX_SEGMENTS < 1 || CE_MAX_SEGMENTS > 255
#error "CE_MAX_SEGMENTS must be 1..255 (ce_set.n_segments is a uint8_t)"
#endif
#if CE_MAX_COEFFS < 1 || CE_MAX_COEFFS > 255
#error "CE_MAX_COEFFS must be 1..255 (ce_set.n_coeffs is a uint8_t)"
#endif
#if CE_MAX_TERMS < 1 || CE_MAX_TERMS > 255
#error "CE_MAX_TERMS must be 1..255 (ce_set.n_terms is a uint8_t)"
#endif
#if CE_MAX_INPUTS < 1 || CE_MAX_INPUTS > 255
#error "CE_MAX_INPUTS must be 1..255 (ce_device.n_inputs and ce_term.input are uint8_t)"
#endif
#if CE_MAX_DEPTH < 1 || CE_MAX_DEPTH > 255
#error "CE_MAX_DEPTH must be 1..255 (the parser keeps a stack of this many levels)"
#endif
#if CE_MAX_SPLINE_KNOTS < 2 || CE_MAX_SPLINE_KNOTS > 255
#error "CE_MAX_SPLINE_KNOTS must be 2..255 (a spline has two knots at least; ce_spline.n_knots is a uint8_t)"
#endif
#if CE_MAX_SPLINES < 1 || CE_MAX_SPLINES > CE_MAX_TERMS
#error "CE_MAX_SPLINES must be 1..CE_MAX_TERMS (each spline belongs to one term; ce_term.spline indexes them)"
#endif

/* Result codes: 0 success, negative refusal. The functions return them as int (so that
 * ce_eval can also return 0 or 1, and the ABI does not depend on the size of an enum). */
typedef enum ce_result {
    CE_OK = 0,
    CE_ERR_ARG = -1,           /* NULL pointer or a ce_set that is not loaded */
    CE_ERR_CRC = -2,           /* CRC32 of the content differs from the declared one */
    CE_ERR_SYNTAX = -3,        /* not JSON, truncated, or trailing bytes */
    CE_ERR_NOT_CANONICAL = -4, /* JSON, but not in canonical form (its CRC would not be the set id) */
    CE_ERR_SCHEMA = -5,        /* schema is not 1 */
    CE_ERR_FIELD = -6,         /* a field missing, of the wrong type, not finite, wrong length */
    CE_ERR_MODEL_KIND = -7,    /* model.kind this library does not evaluate */
    CE_ERR_TERM_KIND = -8,     /* a term kind/feature this library does not evaluate */
    CE_ERR_LIMIT = -9,         /* more segments, coefficients, terms, spline terms, spline knots or
                                  nesting than CE_MAX_*, or a spline knot or piece beyond float range */
    CE_ERR_SENSOR = -10,       /* sensor.id is not this device's serial number */
    CE_ERR_AXIS = -11,         /* sensor.axis is not the bank's axis */
    CE_ERR_SPAN = -12,         /* the span does not reach +-rated range */
    CE_ERR_INPUT = -13,        /* a term reads a channel the device does not offer */
    CE_ERR_COUPLING = -14,     /* coupling matrix with a diagonal term outside CE_COUPLING_MIN_DIAGONAL..
                                  CE_COUPLING_MAX_DIAGONAL, singular (condition above
                                  CE_COUPLING_MAX_CONDITION) or an off-diagonal term above
                                  CE_COUPLING_MAX_OFF_DIAGONAL */
    CE_ERR_IMU_SET = -15,      /* the coupling belongs to another IMU set: the axes given are not its */
    CE_ERR_UNSIGNED = -16,     /* the bank's Signature is empty: the set is not signed */
    CE_ERR_SIGNATURE_FORMAT = -17, /* the Signature is not CE_SIGNATURE_BYTES long (truncated, garbage) */
    CE_ERR_KEY = -18,          /* signed by another key than the device's trust key (key id differs) */
    CE_ERR_SIGNATURE = -19,    /* the signature does not verify: the content changed after signing, or
                                  it was signed for another sensor */
    CE_ERR_ROLLBACK = -20      /* signed with a version below the device's anti-rollback counter */
} ce_result;

/* What the device says about itself; what a set must fit. */
typedef struct {
    uint32_t serial;        /* 0x1018 sub 4; a set's sensor.id must be it in decimal */
    char axis;              /* 'x', 'y' or 'z': the bank's axis */
    float rated_range_dps;  /* 0x2201: the set's span must reach -R..+R (0: not checked) */
    const char *const *inputs; /* names of the run-time channels, e.g. {"temp_c", "supply_v"} */
    uint8_t n_inputs;       /* sample.inputs[i] is the value of inputs[i] */
} ce_device;

/* One sample's inputs. */
typedef struct {
    float raw;              /* raw output, counts */
    uint32_t time_ms;       /* time since power-on (the term input time_s), milliseconds */
    const float *inputs;    /* ce_device.n_inputs channel values (NULL if there are none) */
} ce_sample;

/* One effect term of a loaded set. Internal layout below: read-only to the caller. */
typedef struct {
    uint8_t feature;        /* CE_TERM_* in canical_eval.c */
    uint8_t scale_form;     /* 0: bias (dV' = dV - c x), 1: scale (dV' = dV - c x dV) */
    uint8_t input;          /* channel slot for channel terms */
    uint8_t spline;         /* spline terms: its piecewise cubic, ce_set.splines[spline] */
    float coefficient;
    float reference;
    float inv_tau;          /* 1 / tau_s */
    float threshold;        /* direction threshold, raw units */
    /* state of direction and slope terms */
    float state, high, low, last_raw;
    uint32_t last_ms;
    uint8_t started;
    /* state of a channel's lag and derivative terms: the lag y as a float pair (y + y_err), the
     * running mean's count and start for the first tau (mean_ms: tau in whole milliseconds) */
    uint8_t lagging;
    float y, y_err;
    uint32_t start_ms, count;
    int32_t mean_ms;
} ce_term;

/* A spline term's piecewise cubic (canical.sets.term_kinds.spline_one): knots b_0 < ... < b_m
 * (m + 1 = n_knots), on [b_i, b_i+1] S = a0 + a1 u + a2 u^2 + a3 u^3 with u = w - b_i, w the
 * variable clamped to [b_0, b_m] (flat beyond the end knots). The knots are float pairs
 * (b_i = knot_hi[i] + knot_lo[i] to about 2^-48), so the segment is chosen as in double
 * precision; a rate spline's knots are in raw counts (its dV knots plus V0), compared with the
 * raw output itself. Internal layout: read-only to the caller. */
typedef struct {
    uint8_t n_knots;        /* 2..CE_MAX_SPLINE_KNOTS */
    float knot_hi[CE_MAX_SPLINE_KNOTS], knot_lo[CE_MAX_SPLINE_KNOTS];
    float top_u;            /* u at the last knot: b_m - b_m-1 (the variable clamped from above) */
    float pieces[CE_MAX_SPLINE_KNOTS - 1][4]; /* segment i: a0, a1, a2, a3 */
} ce_spline;

/* A loaded coefficient set: model, effect terms and their run-time state. Built by ce_load()
 * only; read-only to the caller (its size: ce_sizeof_set()). */
typedef struct {
    uint32_t crc;           /* the set's identifier */
    uint8_t loaded;
    uint8_t model;          /* 0 piecewise, 1 forward polynomial */
    uint8_t n_segments, n_coeffs, n_terms;
    uint8_t needs_inputs;   /* a term reads a channel: ce_sample.inputs must be given */
    float v0_hi, v0_lo;     /* zero bias as a float pair (v0_hi + v0_lo) */
    /* Segment points and span edges in raw units as float pairs, so that the segment and the
     * out-of-span flag are decided as in double precision. */
    float knot_hi[CE_MAX_SEGMENTS], knot_lo[CE_MAX_SEGMENTS];
    float lo_hi, lo_lo, hi_hi, hi_lo;
    float dv_lo, dv_hi;     /* span edges in dV */
    float inv_scale;        /* piecewise: 1/scale; forward: 1/rate_scale */
    /* piecewise: segment s's polynomial in t = (dV - seg_mid[s]) * seg_inv_half[s], |t| <= 1
     * inside the segment; forward: the polynomial in u = rate * inv_scale */
    float coeffs[CE_MAX_SEGMENTS][CE_MAX_COEFFS];
    float seg_mid[CE_MAX_SEGMENTS], seg_inv_half[CE_MAX_SEGMENTS];
    float w_lo, w_hi, chord_dv, chord_slope, newton_tol; /* forward polynomial */
    ce_term terms[CE_MAX_TERMS];
    uint8_t n_splines;      /* spline terms of the set, each with its slot below */
    ce_spline splines[CE_MAX_SPLINES];
    uint32_t error_at;      /* byte offset where ce_load refused (for the log) */
} ce_set;

/* ------------------------------------------------------------------------------------------
 * An IMU set's coupling (coupling banks 0x2216/0x2217): corrected = M @ (x, y, z per-axis rates).
 *
 * The coupling bank holds the IMU set's canonical JSON without its "axes" (the matrix, its standard
 * errors, sensor, created, fit) and the IMU set's id: the CRC32 of the whole IMU set, which is the
 * CRC32 of '{"axes":{"x":' X ',"y":' Y ',"z":' Z '},' followed by the coupling content after its
 * '{' (X, Y, Z: the three axis banks' contents; canonical JSON sorts "axes" first). So the device
 * checks, with the bytes it holds, that a coupling belongs to the axes it is activated with.
 * ---------------------------------------------------------------------------------------- */

/* The rules of canical.sets.imu_set.check_coupling: every diagonal term within
 * CE_COUPLING_MIN_DIAGONAL..CE_COUPLING_MAX_DIAGONAL (near identity: each axis's own set fixes its
 * scale), the 2-norm condition number of M at most this, every off-diagonal term's magnitude at
 * most this. */
#define CE_COUPLING_MIN_DIAGONAL 0.5
#define CE_COUPLING_MAX_DIAGONAL 2.0
#define CE_COUPLING_MAX_CONDITION 1e3
#define CE_COUPLING_MAX_OFF_DIAGONAL 0.10

/* A loaded coupling. Built by ce_coupling_load() only; read-only to the caller (its size:
 * ce_sizeof_coupling()). */
typedef struct {
    uint32_t crc;           /* the coupling bank's CRC32 */
    uint32_t imu_set_id;    /* the IMU set's CRC32 */
    uint32_t axis_crc[3];   /* the x, y, z sets it belongs to (ce_set.crc) */
    uint8_t loaded;
    /* M as the identity plus a small part, so the coupled rate is r + (small part @ r): the
     * float32 rounding is that of a small correction, not of a product the rate's size */
    float delta[3][3];      /* M - I, row-major */
    uint32_t error_at;      /* byte offset where ce_coupling_load refused (for the log) */
} ce_coupling;

/* Three axes' raw outputs of one sample. */
typedef struct {
    float raw[3];           /* x, y, z, counts */
    uint32_t time_ms;       /* time since power-on, milliseconds */
    const float *inputs;    /* ce_device.n_inputs channel values (NULL if there are none); the three
                               sets must have been loaded with the same ce_device.inputs */
} ce_sample3;

/* Validate a coupling bank (content + declared CRC + the IMU set id it declares) for `device`
 * (its serial; axis and rated range are not used) against the three axis banks it is to run
 * with (axis_content[i], axis_length[i]: x, y, z), and build `coupling`. Checks: CRC, canonical
 * JSON, schema 1, kind "imu-set", no "axes" key, sensor.id the device's serial, coupling.matrix
 * 3 rows of 3 finite numbers within the CE_COUPLING_* limits, and that the axis banks and this
 * content make the IMU set `imu_set_id` names (else CE_ERR_IMU_SET). Returns CE_OK or a negative
 * CE_ERR_*; on refusal `coupling` is marked not loaded. */
int ce_coupling_load(ce_coupling *coupling, const uint8_t *content, uint32_t length, uint32_t declared_crc,
                     uint32_t imu_set_id, const uint8_t *const axis_content[3], const uint32_t axis_length[3],
                     const ce_device *device);

/* Correct one three-axis sample: each axis with its set (ce_eval), then the coupling (NULL: the
 * identity, a device without a coupling). rate_dps[i] in deg/s, out_of_span[i] 1 when axis i's
 * raw value lies outside its set's span. Returns CE_OK, CE_ERR_ARG (a NULL pointer, a set or the
 * coupling not loaded) or CE_ERR_IMU_SET (the sets are not the ones the coupling belongs to). */
int ce_eval3(ce_set *const axes[3], const ce_coupling *coupling, const ce_sample3 *sample, float rate_dps[3],
             uint8_t out_of_span[3]);

/* ce_eval3 over n samples in time order: raw, rate_dps and out_of_span hold 3 values per sample
 * (x, y, z), inputs n_inputs per sample (NULL: none), time_ms may be NULL (time 0). */
int ce_eval3_block(ce_set *const axes[3], const ce_coupling *coupling, uint32_t n, const float *raw,
                   const uint32_t *time_ms, const float *inputs, uint8_t n_inputs, float *rate_dps,
                   uint8_t *out_of_span);

/* ------------------------------------------------------------------------------------------
 * Signed sets: the check before activation, once the device has a trust key.
 *
 * A bank's "Signature" sub-index (0x2210-0x2217, sub 5 of an axis bank, sub 6 of a coupling bank)
 * holds CE_SIGNATURE_BYTES: the set's version (uint64, little-endian), the signing key's id (the
 * first CE_KEY_ID_BYTES of the SHA-256 of its public key) and the Ed25519 signature. The signed
 * message is "canical signed set v1\n" '{"sensor":"SERIAL","version":N}' "\n" and the set's
 * canonical content (SERIAL and N in decimal): for an axis bank its content, for an IMU set the
 * whole IMU set rebuilt from the coupling bank and the three axis banks as ce_coupling_load does.
 * The cryptography is not here: the device gives its vendor's Ed25519 verification as a function.
 * Checks, in this order (the emulated IMU's order, so both give the same refusal): signed at all,
 * the length, the key id, the signature, the version against the counter.
 * ---------------------------------------------------------------------------------------- */

#define CE_SIGNATURE_BYTES 80 /* version (8) + key id (8) + Ed25519 signature (64) */
#define CE_KEY_ID_BYTES 8
#define CE_ED25519_BYTES 64
#define CE_PUBLIC_KEY_BYTES 32
#define CE_SIGNED_HEADER_MAX 80 /* the domain and '{"sensor":...,"version":...}\n' at most, bytes */

/* The device's Ed25519 verification: 0 when `signature` (CE_ED25519_BYTES) is a valid signature by
 * `public_key` (CE_PUBLIC_KEY_BYTES) of message[0..length), anything else when not (libsodium's
 * crypto_sign_verify_detached has this meaning). `context` is ce_trust.context, passed through. */
typedef int (*ce_verify_fn)(void *context, const uint8_t *signature, const uint8_t *message, uint32_t length,
                            const uint8_t *public_key);

/* What the device trusts, and the room to check with. */
typedef struct {
    const uint8_t *public_key;   /* the provisioned key, CE_PUBLIC_KEY_BYTES */
    const uint8_t *key_id;       /* its id, CE_KEY_ID_BYTES (computed once, at provisioning) */
    uint64_t counter;            /* the anti-rollback counter: the highest version ever activated */
    ce_verify_fn verify;         /* the vendor's verification */
    void *context;               /* passed to verify */
    uint8_t *scratch;            /* where the signed message is built (no heap): at least
                                    CE_SIGNED_HEADER_MAX plus the bytes signed */
    uint32_t scratch_size;
} ce_trust;

/* Check an axis bank's signature (`signature`, `signature_length` bytes: the Signature sub-index as
 * written) over its content for the device with serial `serial`, before activating it. Returns
 * CE_OK and the signed version in *version (raise the counter to it once activated), or
 * CE_ERR_UNSIGNED, CE_ERR_SIGNATURE_FORMAT, CE_ERR_KEY, CE_ERR_SIGNATURE, CE_ERR_ROLLBACK,
 * CE_ERR_LIMIT (scratch too small) or CE_ERR_ARG (a NULL pointer). Check the content itself
 * (ce_load) too: a signature says who made the bytes, not that this device can run them. */
int ce_signature_check(const ce_trust *trust, const uint8_t *signature, uint32_t signature_length,
                       const uint8_t *content, uint32_t length, uint32_t serial, uint64_t *version);

/* The same for an IMU set: the signature on its coupling bank covers the whole IMU set, rebuilt
 * from the coupling bank's content and the three axis banks (x, y, z) it is activated with. */
int ce_signature_check3(const ce_trust *trust, const uint8_t *signature, uint32_t signature_length,
                        const uint8_t *content, uint32_t length, const uint8_t *const axis_content[3],
                        const uint32_t axis_length[3], uint32_t serial, uint64_t *version);

/* sizeof(ce_coupling), for bindings that treat it as opaque bytes. */
uint32_t ce_sizeof_coupling(void);

/* zlib's CRC32 (the bank CRC) of `length` bytes; 0 for a NULL `data`. */
uint32_t ce_crc32(const uint8_t *data, uint32_t length);

/* Validate a bank (content + declared CRC) for `device` and build `set` from it.
 * Returns CE_OK or a negative CE_ERR_*; on refusal `set` is marked not loaded (load into a
 * scratch ce_set and copy it over the running one only when every axis passed). */
int ce_load(ce_set *set, const uint8_t *content, uint32_t length, uint32_t declared_crc,
            const ce_device *device);

/* Forget direction, slope, lag and derivative state (a new stream of samples begins). */
void ce_reset(ce_set *set);

/* Correct the next sample of the stream: *rate_dps in deg/s. Returns 1 when the sample
 * lies outside the calibrated span (rate extrapolated linearly), 0 inside, CE_ERR_ARG when
 * the set is not loaded. */
int ce_eval(ce_set *set, const ce_sample *sample, float *rate_dps);

/* ce_eval over n samples in time order; inputs holds n_inputs values per sample (NULL: none),
 * time_ms may be NULL (time 0). Writes rate_dps[0..n) and out_of_span[0..n) (1 outside the
 * span); returns CE_OK, or CE_ERR_ARG (a NULL pointer, the set not loaded, inputs missing). */
int ce_eval_block(ce_set *set, uint32_t n, const float *raw, const uint32_t *time_ms,
                  const float *inputs, uint8_t n_inputs, float *rate_dps, uint8_t *out_of_span);

/* Fixed-point form of a loaded piecewise set without effect terms, for an MCU without an FPU:
 * integer raw counts in (|raw - v0| < 65536: a 16-bit sensor), rate in 1/65536 deg/s out,
 * int32/int64 add, multiply and shift only (within 1e-3 deg/s of the float form on canical's
 * tests, a tenth of the corrected frame's 0.01 deg/s LSB). */
typedef struct {
    uint8_t loaded, n_segments, n_coeffs;
    int32_t lo, hi;                     /* raw inside the span: lo <= raw <= hi */
    int32_t knot[CE_MAX_SEGMENTS];      /* segment s + 1 starts at raw >= knot[s] */
    int64_t v0_q16;                     /* zero bias, counts * 2^16 */
    int64_t edge_lo_q30, edge_hi_q30;   /* t at the span edges (first, last segment), 2^30 */
    int64_t mid_q16[CE_MAX_SEGMENTS];   /* segment centre, dV counts * 2^16 */
    int64_t t_mult[CE_MAX_SEGMENTS];    /* t_q30 = ((dv_q16 - mid_q16) * t_mult) >> t_shift */
    int32_t t_shift[CE_MAX_SEGMENTS];
    int32_t coeffs[CE_MAX_SEGMENTS][CE_MAX_COEFFS]; /* in t, deg/s * 2^16 */
} ce_fixed;

/* CE_OK, or CE_ERR_MODEL_KIND (forward polynomial), CE_ERR_TERM_KIND (effect terms),
 * CE_ERR_LIMIT (coefficients or u beyond the fixed-point ranges). */
int ce_fixed_from(ce_fixed *fixed, const ce_set *set);

/* Rate of one integer sample in 1/65536 deg/s; returns 1 out of span, 0 inside, CE_ERR_ARG. */
int ce_fixed_eval(const ce_fixed *fixed, int32_t raw, int32_t *rate_q16);

/* sizeof(ce_set), for bindings that treat it as opaque bytes (canical's ctypes wrapper). */
uint32_t ce_sizeof_set(void);
/* sizeof(ce_fixed), likewise. */
uint32_t ce_sizeof_fixed(void);
/* The byte offset in the content where the last ce_load() refused (0 for a NULL set). */
uint32_t ce_error_offset(const ce_set *set);

/* A short English name of a result code (a ce_result); "unknown code" for any other value. */
const char *ce_strerror(int code);

#ifdef __cplusplus
}
#endif
#endif
