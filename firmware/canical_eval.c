/*
 * canical_eval: validate a coefficient bank and correct samples with it (see canical_eval.h).
 *
 * The bank content is canonical JSON (sorted keys, no white space, Python's shortest
 * round-trip float spelling, ASCII with \u escapes): the bytes the set's CRC32 covers. The
 * parser below reads exactly that grammar without recursion and without the heap; anything
 * else is refused. It checks everything canical's own loader checks (canical/sets/coefficient_file.py,
 * canical/sets/terms.py) and the device's admission rules (canical/sets/admission.py), except that it
 * does not prove a float spelling is the *shortest* round trip (it checks the form only).
 *
 * Adding a term kind: one row in TERM_SPECS and one case in term_feature() (which gets the
 * sample's dv = raw - V0 for terms that read the output, as a rate-gated channel does). A kind
 * with NEEDS_SPLINE carries a piecewise cubic (knots, pieces) in a ce_set.splines slot, evaluated
 * by spline_at() of whichever variable the kind names.
 *
 * MIT licence, like the rest of canical.
 */
#include "canical_eval.h"

#include <float.h>
#include <stddef.h>

/* Internal invariants (like libcanard's CANARD_ASSERT): assert() in a hosted build, nothing with
 * NDEBUG or freestanding (no C library there); a build may define CE_ASSERT itself. */
#ifndef CE_ASSERT
#if defined(NDEBUG) || !defined(__STDC_HOSTED__) || !__STDC_HOSTED__
#define CE_ASSERT(x) ((void)0)
#else
#include <assert.h>
#define CE_ASSERT(x) assert(x)
#endif
#endif

/* No <string.h>: the library builds freestanding (-ffreestanding, no C library at all). */
static size_t text_length(const char *s)
{
    size_t n = 0;
    while (s[n] != '\0') {
        n++;
    }
    return n;
}

static int same_bytes(const uint8_t *a, const char *b, size_t n)
{
    size_t i;
    for (i = 0; i < n; i++) {
        if (a[i] != (uint8_t)b[i]) {
            return 0;
        }
    }
    return 1;
}

static void zero(void *p, size_t n)
{
    volatile uint8_t *b = (volatile uint8_t *)p;
    size_t i;
    for (i = 0; i < n; i++) {
        b[i] = 0u;
    }
}

/* ------------------------------------------------------------------------------------------
 * CRC32 (zlib), four bits at a time: a 64-byte table instead of 1 KB.
 * ---------------------------------------------------------------------------------------- */

static const uint32_t CRC_NIBBLE[16] = {
    0x00000000u, 0x1DB71064u, 0x3B6E20C8u, 0x26D930ACu, 0x76DC4190u, 0x6B6B51F4u,
    0x4DB26158u, 0x5005713Cu, 0xEDB88320u, 0xF00F9344u, 0xD6D6A3E8u, 0xCB61B38Cu,
    0x9B64C2B0u, 0x86D3D2D4u, 0xA00AE278u, 0xBDBDF21Cu};

/* The running register over more bytes (start from 0xFFFFFFFF, invert at the end): one CRC over
 * pieces, as the IMU set id is over its axis banks and its coupling bank. */
static uint32_t crc_update(uint32_t crc, const uint8_t *data, uint32_t length)
{
    uint32_t i;
    for (i = 0; i < length; i++) {
        crc ^= data[i];
        crc = (crc >> 4) ^ CRC_NIBBLE[crc & 15u];
        crc = (crc >> 4) ^ CRC_NIBBLE[crc & 15u];
    }
    return crc;
}

static uint32_t crc_text(uint32_t crc, const char *text)
{
    return crc_update(crc, (const uint8_t *)text, (uint32_t)text_length(text));
}

uint32_t ce_crc32(const uint8_t *data, uint32_t length)
{
    if (data == NULL) {
        return 0u;
    }
    return ~crc_update(0xFFFFFFFFu, data, length);
}

/* ------------------------------------------------------------------------------------------
 * Term kinds: (kind, feature) as the set names them -> evaluator code and required fields.
 * ---------------------------------------------------------------------------------------- */

enum {
    CE_TERM_CHANNEL_OFFSET = 1,
    CE_TERM_CHANNEL_SQUARE,
    CE_TERM_CHANNEL_LAG,        /* stateful channel transforms (canical.sets.terms.ChannelTracker) */
    CE_TERM_CHANNEL_DERIVATIVE,
    CE_TERM_CHANNEL_DIRECTION,
    CE_TERM_TIME_WARMUP,
    CE_TERM_TIME_LINEAR,
    CE_TERM_DIRECTION_SIGN,
    CE_TERM_DIRECTION_SLOPE
};

/* A channel's level beyond a knee in |dv| (canical.sets.terms "gated"): its own code, apart from the list. */
enum { CE_TERM_CHANNEL_GATED = 64 };

/* Piecewise cubics (canical.sets.term_kinds.ChannelSpline): S(v) of the channel, the channel's
 * offset times R(dV) of the output (ChannelRateSpline), and S of the channel's lag y or of its
 * smoothed rate of change (v - y)/tau (ChannelLagSpline, ChannelDerivativeSpline: the lag's state,
 * as CE_TERM_CHANNEL_LAG keeps it); all through spline_at(). */
enum {
    CE_TERM_CHANNEL_SPLINE = 65,
    CE_TERM_CHANNEL_RATE_SPLINE = 66,
    CE_TERM_CHANNEL_LAG_SPLINE = 67,
    CE_TERM_CHANNEL_DERIVATIVE_SPLINE = 68
};

#define NEEDS_CHANNEL 1u
#define NEEDS_TAU 2u
#define NEEDS_THRESHOLD 4u
#define NEEDS_SPLINE 8u

typedef struct {
    const char *kind;
    const char *feature;
    uint8_t code;
    uint8_t needs;
} term_spec;

static const term_spec TERM_SPECS[] = {
    {"channel", "gated", CE_TERM_CHANNEL_GATED, NEEDS_CHANNEL | NEEDS_THRESHOLD},
    {"channel", "offset", CE_TERM_CHANNEL_OFFSET, NEEDS_CHANNEL},
    {"channel", "square", CE_TERM_CHANNEL_SQUARE, NEEDS_CHANNEL},
    {"channel", "lag", CE_TERM_CHANNEL_LAG, NEEDS_CHANNEL | NEEDS_TAU},
    {"channel", "derivative", CE_TERM_CHANNEL_DERIVATIVE, NEEDS_CHANNEL | NEEDS_TAU},
    {"channel", "direction", CE_TERM_CHANNEL_DIRECTION, NEEDS_CHANNEL | NEEDS_THRESHOLD},
    {"channel", "spline", CE_TERM_CHANNEL_SPLINE, NEEDS_CHANNEL | NEEDS_SPLINE},
    {"channel", "rate_spline", CE_TERM_CHANNEL_RATE_SPLINE, NEEDS_CHANNEL | NEEDS_SPLINE},
    {"channel", "lag_spline", CE_TERM_CHANNEL_LAG_SPLINE, NEEDS_CHANNEL | NEEDS_TAU | NEEDS_SPLINE},
    {"channel", "derivative_spline", CE_TERM_CHANNEL_DERIVATIVE_SPLINE, NEEDS_CHANNEL | NEEDS_TAU | NEEDS_SPLINE},
    {"time", "warmup", CE_TERM_TIME_WARMUP, NEEDS_TAU},
    {"time", "linear", CE_TERM_TIME_LINEAR, 0u},
    {"direction", "sign", CE_TERM_DIRECTION_SIGN, NEEDS_THRESHOLD},
    {"direction", "slope", CE_TERM_DIRECTION_SLOPE, NEEDS_TAU},
};

#define N_TERM_SPECS (sizeof TERM_SPECS / sizeof TERM_SPECS[0])

/* ------------------------------------------------------------------------------------------
 * Float helpers: only add, multiply, divide, compare (Cortex-M4F hardware).
 * ---------------------------------------------------------------------------------------- */

static float absf(float x) { return x < 0.0f ? -x : x; }

/* 2^k for -126 <= k <= 127, from the bits. */
static float pow2f(int k)
{
    union {
        uint32_t u;
        float f;
    } v;
    v.u = (uint32_t)(k + 127) << 23;
    return v.f;
}

/* exp(x) - 1, accurate to a few ulp also for small |x| (where 1 - exp(-x) would cancel):
 * x = k ln2 + r with |r| <= ln2/2, a degree-7 Taylor polynomial for expm1(r). */
static float expm1_f(float x)
{
    const float ln2_hi = 0.693145751953125f; /* few bits: k * ln2_hi is exact */
    const float ln2_lo = 1.428606765330187e-06f;
    float kf, r, p, two_k;
    int k;
    if (!(x == x)) {
        return x; /* NaN */
    }
    if (x > 88.0f) {
        return FLT_MAX;
    }
    if (x < -25.0f) {
        return -1.0f;
    }
    kf = x * 1.4426950408889634f;
    k = (int)(kf < 0.0f ? kf - 0.5f : kf + 0.5f);
    r = (x - (float)k * ln2_hi) - (float)k * ln2_lo;
    p = r * r * (0.5f + r * (1.0f / 6 + r * (1.0f / 24 + r * (1.0f / 120 + r * (1.0f / 720 + r * (1.0f / 5040))))));
    p = r + p; /* expm1(r) */
    if (k == 0) {
        return p;
    }
    two_k = pow2f(k);
    return two_k * p + (two_k - 1.0f);
}

/* float pair (hi, lo) with hi + lo = d to about 2^-48 relative. */
static void split(double d, float *hi, float *lo)
{
    *hi = (float)d;
    *lo = (float)(d - (double)*hi);
}

/* ------------------------------------------------------------------------------------------
 * Canonical JSON reader.
 * ---------------------------------------------------------------------------------------- */

typedef struct {
    const uint8_t *base;
    const uint8_t *p;
    const uint8_t *end;
    int err;
    uint32_t err_at;
} cur;

static int fail(cur *c, int code)
{
    if (c->err == 0) {
        c->err = code;
        c->err_at = (uint32_t)(c->p - c->base);
    }
    return c->err;
}

/* Next byte without consuming it, -1 at the end. White space is valid JSON but never
 * canonical, so it is refused as such wherever a token may start. */
static int tok(cur *c)
{
    int b;
    if (c->p >= c->end) {
        return -1;
    }
    b = *c->p;
    if (b == ' ' || b == '\t' || b == '\n' || b == '\r') {
        fail(c, CE_ERR_NOT_CANONICAL);
        return -1;
    }
    return b;
}

static int expect(cur *c, int ch)
{
    if (tok(c) != ch) {
        return fail(c, CE_ERR_SYNTAX);
    }
    c->p++;
    return 0;
}

static int is_digit(int b) { return b >= '0' && b <= '9'; }

static int hex_value(int b)
{
    if (is_digit(b)) {
        return b - '0';
    }
    if (b >= 'a' && b <= 'f') {
        return b - 'a' + 10;
    }
    if (b >= 'A' && b <= 'F') {
        return 16 + b - 'A'; /* valid JSON, but canonical escapes are lower case */
    }
    return -1;
}

/* A string; *s, *n: its bytes between the quotes (escapes not decoded), *escaped if any. */
static int parse_string(cur *c, const uint8_t **s, uint32_t *n, int *escaped)
{
    const uint8_t *start;
    *escaped = 0;
    if (expect(c, '"')) {
        return c->err;
    }
    start = c->p;
    while (c->p < c->end) {
        int b = *c->p;
        if (b == '"') {
            *s = start;
            *n = (uint32_t)(c->p - start);
            c->p++;
            return 0;
        }
        if (b < 0x20) {
            return fail(c, CE_ERR_SYNTAX);
        }
        if (b >= 0x7f) {
            return fail(c, CE_ERR_NOT_CANONICAL); /* canonical JSON is ASCII, \u-escaped */
        }
        if (b == '\\') {
            int e;
            *escaped = 1;
            c->p++;
            if (c->p >= c->end) {
                return fail(c, CE_ERR_SYNTAX);
            }
            e = *c->p;
            if (e == '"' || e == '\\' || e == 'b' || e == 'f' || e == 'n' || e == 'r' || e == 't') {
                c->p++;
            } else if (e == '/') {
                return fail(c, CE_ERR_NOT_CANONICAL);
            } else if (e == 'u') {
                int i, v = 0, upper = 0;
                c->p++;
                for (i = 0; i < 4; i++) {
                    int h = c->p < c->end ? hex_value(*c->p) : -1;
                    if (h < 0) {
                        return fail(c, CE_ERR_SYNTAX);
                    }
                    if (h >= 16) {
                        upper = 1;
                        h -= 6;
                    }
                    v = v * 16 + h;
                    c->p++;
                }
                if (upper || v == 8 || v == 9 || v == 10 || v == 12 || v == 13 || (v >= 0x20 && v < 0x7f)) {
                    return fail(c, CE_ERR_NOT_CANONICAL);
                }
            } else {
                return fail(c, CE_ERR_SYNTAX);
            }
        } else {
            c->p++;
        }
    }
    return fail(c, CE_ERR_SYNTAX);
}

static const double POW10[23] = {1e0,  1e1,  1e2,  1e3,  1e4,  1e5,  1e6,  1e7,  1e8,  1e9,  1e10, 1e11,
                                 1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22};

/* m * 10^e, m an exact integer; within a few ulp (exact for the common |e| <= 22, m < 2^53). */
static double scale10(double m, int e)
{
    if (e > 330) {
        return m * 1e300 * 1e300; /* overflow: inf, refused as not finite */
    }
    if (e < -360) {
        return 0.0;
    }
    while (e > 22) {
        m *= 1e22;
        e -= 22;
    }
    while (e < -22) {
        m /= 1e22;
        e += 22;
    }
    return e >= 0 ? m * POW10[e] : m / POW10[-e];
}

/* The parts of a number as scanned: up to 19 significant digits as an integer, the power of
 * ten that places them, and what the canonical-form check needs to know of each part. */
typedef struct {
    uint64_t m;          /* the first (at most 19) significant digits */
    int sig;             /* digits in m */
    int nsig;            /* significant digits written */
    int dexp;            /* value = m * 10^(dexp + exponent) */
    int nonzero;         /* a nonzero digit has been seen */
    int neg, int_zero, int_digits;
    int has_frac, frac_digits, frac_lead_zeros, frac_last;
    int has_exp, exp_neg, exp_digits, exp_first, exp_val;
} numeral;

/* One significant digit: into m while it holds 19 digits. A fraction digit kept moves the point
 * left; an integer digit beyond the 19 still counts a place; a fraction digit beyond them is dropped. */
static void significant_digit(numeral *n, int d, int in_fraction)
{
    n->nonzero = 1;
    n->nsig++;
    if (n->sig < 19) {
        n->m = n->m * 10u + (uint64_t)d;
        n->sig++;
        n->dexp -= in_fraction;
    } else {
        n->dexp += !in_fraction;
    }
}

/* The integer part: "0" alone, or digits without a leading zero. */
static int scan_integer_part(cur *c, numeral *n)
{
    int b = c->p < c->end ? *c->p : -1;
    if (!is_digit(b)) {
        return fail(c, CE_ERR_SYNTAX);
    }
    if (b == '0') {
        n->int_zero = 1;
        n->int_digits = 1;
        c->p++;
        if (c->p < c->end && is_digit(*c->p)) {
            return fail(c, CE_ERR_SYNTAX); /* leading zero */
        }
        return 0;
    }
    while (c->p < c->end && is_digit(*c->p)) {
        significant_digit(n, *c->p - '0', 0);
        n->int_digits++;
        c->p++;
    }
    return 0;
}

/* The fraction after '.', if any: at least one digit; leading zeros only move the point. */
static int scan_fraction(cur *c, numeral *n)
{
    if (!(c->p < c->end && *c->p == '.')) {
        return 0;
    }
    n->has_frac = 1;
    c->p++;
    if (!(c->p < c->end && is_digit(*c->p))) {
        return fail(c, CE_ERR_SYNTAX);
    }
    while (c->p < c->end && is_digit(*c->p)) {
        int d = *c->p - '0';
        if (!n->nonzero && d == 0) {
            n->frac_lead_zeros++;
            n->dexp--;
        } else {
            significant_digit(n, d, 1);
        }
        n->frac_last = d;
        n->frac_digits++;
        c->p++;
    }
    return 0;
}

/* The exponent, if any: 'e', a sign (always written), digits (their value capped). */
static int scan_exponent(cur *c, numeral *n)
{
    if (!(c->p < c->end && (*c->p == 'e' || *c->p == 'E'))) {
        return 0;
    }
    n->has_exp = 1;
    if (*c->p == 'E') {
        return fail(c, CE_ERR_NOT_CANONICAL);
    }
    c->p++;
    if (c->p < c->end && (*c->p == '+' || *c->p == '-')) {
        n->exp_neg = *c->p == '-';
        c->p++;
    } else {
        return fail(c, c->p < c->end && is_digit(*c->p) ? CE_ERR_NOT_CANONICAL : CE_ERR_SYNTAX);
    }
    if (!(c->p < c->end && is_digit(*c->p))) {
        return fail(c, CE_ERR_SYNTAX);
    }
    n->exp_first = *c->p - '0';
    while (c->p < c->end && is_digit(*c->p)) {
        if (n->exp_val < 100000) {
            n->exp_val = n->exp_val * 10 + (*c->p - '0');
        }
        n->exp_digits++;
        c->p++;
    }
    return 0;
}

/* Canonical form (Python's repr): ints plain; floats fixed for 1e-4 <= |x| < 1e16, else
 * d[.ddd]e+XX; no trailing zeros in a fraction (but "x.0"); at most 17 digits. */
static int is_canonical(const numeral *n)
{
    if (n->has_exp) {
        int small_enough = n->exp_neg ? n->exp_val >= 5 : n->exp_val >= 16;
        return !(n->int_zero || n->int_digits != 1 || (n->has_frac && n->frac_last == 0) || n->nsig > 17 ||
                 n->exp_digits < 2 || (n->exp_digits > 2 && n->exp_first == 0) || !small_enough);
    }
    if (n->has_frac) {
        int zero_frac = n->frac_digits == 1 && n->frac_last == 0;
        return !(n->nsig > 17 || n->int_digits > 16 || (!zero_frac && n->frac_last == 0) ||
                 (n->int_zero && !zero_frac && n->frac_lead_zeros > 3));
    }
    return !(n->neg && n->int_zero); /* -0 is written 0 */
}

/* A number in the form Python's json.dumps writes it (int, or float repr). */
static int parse_number(cur *c, double *out)
{
    numeral n;
    zero(&n, sizeof n);
    n.frac_last = -1;
    if (tok(c) == '-') {
        n.neg = 1;
        c->p++;
    }
    if (scan_integer_part(c, &n) || scan_fraction(c, &n) || scan_exponent(c, &n)) {
        return c->err;
    }
    if (!is_canonical(&n)) {
        return fail(c, CE_ERR_NOT_CANONICAL);
    }
    if (n.m == 0) {
        *out = n.neg ? -0.0 : 0.0;
        return 0;
    }
    *out = scale10((double)n.m, n.dexp + (n.exp_neg ? -n.exp_val : n.exp_val));
    if (*out == 0.0 || !(*out - *out == 0.0)) {
        return fail(c, CE_ERR_NOT_CANONICAL); /* 0.0 or beyond float range: never written so */
    }
    if (n.neg) {
        *out = -*out;
    }
    return 0;
}

static int match_literal(cur *c, const char *lit)
{
    size_t n = text_length(lit);
    if ((size_t)(c->end - c->p) < n || !same_bytes(c->p, lit, n)) {
        return fail(c, CE_ERR_SYNTAX);
    }
    c->p += n;
    return 0;
}

/* Strictly ascending keys (canonical: sorted, no duplicates). */
static int key_after(const uint8_t *prev, uint32_t prev_n, const uint8_t *k, uint32_t n)
{
    uint32_t i, common = prev_n < n ? prev_n : n;
    if (prev == NULL) {
        return 1;
    }
    for (i = 0; i < common; i++) {
        if (k[i] != prev[i]) {
            return k[i] > prev[i];
        }
    }
    return n > prev_n;
}

/* An object key: plain ASCII (an escaped key is valid JSON but not one this library reads). */
static int parse_key(cur *c, const uint8_t **prev, uint32_t *prev_n)
{
    const uint8_t *k;
    uint32_t n;
    int escaped;
    if (parse_string(c, &k, &n, &escaped)) {
        return c->err;
    }
    if (escaped) {
        return fail(c, CE_ERR_FIELD);
    }
    if (!key_after(*prev, *prev_n, k, n)) {
        return fail(c, CE_ERR_NOT_CANONICAL);
    }
    *prev = k;
    *prev_n = n;
    return expect(c, ':');
}

static int parse_scalar(cur *c)
{
    int b = tok(c);
    const uint8_t *s;
    uint32_t n;
    int escaped;
    double d;
    if (c->err) {
        return c->err;
    }
    if (b == '"') {
        return parse_string(c, &s, &n, &escaped);
    }
    if (b == '-' || is_digit(b)) {
        return parse_number(c, &d);
    }
    if (b == 't') {
        return match_literal(c, "true");
    }
    if (b == 'f') {
        return match_literal(c, "false");
    }
    if (b == 'n') {
        return match_literal(c, "null");
    }
    return fail(c, CE_ERR_SYNTAX);
}

/* Any value, checked and skipped, with an explicit stack instead of recursion. */
static int skip_value(cur *c)
{
    uint8_t is_obj[CE_MAX_DEPTH];
    const uint8_t *last[CE_MAX_DEPTH];
    uint32_t last_n[CE_MAX_DEPTH];
    int depth = 0;
    for (;;) {
        int b = tok(c);
        if (c->err) {
            return c->err;
        }
        if (b == '{' || b == '[') {
            if (depth == CE_MAX_DEPTH) {
                return fail(c, CE_ERR_LIMIT);
            }
            CE_ASSERT(depth >= 0 && depth < CE_MAX_DEPTH);
            c->p++;
            is_obj[depth] = (uint8_t)(b == '{');
            last[depth] = NULL;
            last_n[depth] = 0;
            depth++;
            if (tok(c) == (b == '{' ? '}' : ']')) {
                c->p++;
                depth--;
            } else {
                if (is_obj[depth - 1] && parse_key(c, &last[depth - 1], &last_n[depth - 1])) {
                    return c->err;
                }
                continue; /* the first member's value */
            }
        } else if (parse_scalar(c)) {
            return c->err;
        }
        /* a value ended: close containers or move to the next member */
        for (;;) {
            int close;
            if (depth == 0) {
                return 0;
            }
            close = is_obj[depth - 1] ? '}' : ']';
            b = tok(c);
            if (b == close) {
                c->p++;
                depth--;
                continue;
            }
            if (b != ',') {
                return fail(c, CE_ERR_SYNTAX);
            }
            c->p++;
            if (is_obj[depth - 1] && parse_key(c, &last[depth - 1], &last_n[depth - 1])) {
                return c->err;
            }
            break;
        }
    }
}

/* Members of an object in order: 1 with the cursor at the value of *key, 0 at the end. */
typedef struct {
    const uint8_t *key;
    uint32_t n;
    int started;
} members;

static int next_member(cur *c, members *it)
{
    int b;
    if (!it->started) {
        it->started = 1;
        if (tok(c) != '{') {
            return fail(c, c->err ? c->err : CE_ERR_FIELD); /* not an object where one belongs */
        }
        c->p++;
        if (tok(c) == '}') {
            c->p++;
            return 0;
        }
    } else {
        b = tok(c);
        if (b == '}') {
            c->p++;
            return 0;
        }
        if (b != ',') {
            return fail(c, CE_ERR_SYNTAX);
        }
        c->p++;
    }
    if (c->err) {
        return c->err;
    }
    return parse_key(c, &it->key, &it->n) ? c->err : 1;
}

static int key_is(const members *it, const char *name)
{
    size_t n = text_length(name);
    return it->n == n && same_bytes(it->key, name, n);
}

/* Elements of an array: 1 when one follows, 0 at the end. */
static int next_element(cur *c, int *started)
{
    int b;
    if (!*started) {
        *started = 1;
        if (tok(c) != '[') {
            return fail(c, c->err ? c->err : CE_ERR_FIELD);
        }
        c->p++;
        if (tok(c) == ']') {
            c->p++;
            return 0;
        }
        return c->err ? c->err : 1;
    }
    b = tok(c);
    if (b == ']') {
        c->p++;
        return 0;
    }
    if (b != ',') {
        return fail(c, CE_ERR_SYNTAX);
    }
    c->p++;
    return 1;
}

/* A finite number (not a boolean, not null). */
static int number_value(cur *c, double *d)
{
    int b = tok(c);
    if (c->err) {
        return c->err;
    }
    if (!(b == '-' || is_digit(b))) {
        return fail(c, CE_ERR_FIELD);
    }
    if (parse_number(c, d)) {
        return c->err;
    }
    if (!(*d - *d == 0.0)) {
        return fail(c, CE_ERR_FIELD); /* inf */
    }
    return 0;
}

/* A number or null (*present = 0). */
static int optional_number(cur *c, double *d, int *present)
{
    if (tok(c) == 'n') {
        *present = 0;
        return match_literal(c, "null");
    }
    *present = 1;
    return number_value(c, d);
}

/* A list of at most `cap` finite numbers (more: CE_ERR_LIMIT). */
static int number_list(cur *c, double *out, int cap, int *count)
{
    int started = 0, r;
    *count = 0;
    while ((r = next_element(c, &started)) == 1) {
        double d;
        if (*count == cap) {
            return fail(c, CE_ERR_LIMIT);
        }
        if (number_value(c, &d)) {
            return c->err;
        }
        out[(*count)++] = d;
    }
    return r;
}

static int string_value(cur *c, const uint8_t **s, uint32_t *n)
{
    int escaped;
    if (tok(c) != '"') {
        return fail(c, c->err ? c->err : CE_ERR_FIELD);
    }
    return parse_string(c, s, n, &escaped);
}

static int bytes_are(const uint8_t *s, uint32_t n, const char *text)
{
    size_t len = text_length(text);
    return s != NULL && n == len && same_bytes(s, text, len);
}

/* ------------------------------------------------------------------------------------------
 * The set as read, before the device's checks.
 * ---------------------------------------------------------------------------------------- */

enum { KIND_NONE = -1, KIND_SEG_INVERSE, KIND_SEG_LINEAR, KIND_FORWARD };

typedef struct {
    int have_schema, have_sensor, have_units, have_model, have_v0, schema_ok;
    double v0;
    const uint8_t *sensor_id, *sensor_axis;
    uint32_t sensor_id_n, sensor_axis_n;
    int kind;
    int have_knots, n_knots, have_span, have_scale, have_rate_scale, have_rate_span;
    double knots[CE_MAX_SEGMENTS];
    double span[2], scale, rate_scale, rate_span[2];
    int coeff_rows; /* -1: flat list, 0 none, >0 rows of a matrix */
    int coeff_width, have_coeffs;
    double flat[CE_MAX_COEFFS];
    double matrix[CE_MAX_SEGMENTS][CE_MAX_COEFFS]; /* double until derive() re-centres them */
    int n_terms;
    const uint8_t *channel[CE_MAX_TERMS];
    uint32_t channel_n[CE_MAX_TERMS];
} reading;

static int parse_coefficients(cur *c, reading *r)
{
    int started = 0, more;
    r->have_coeffs = 1;
    r->coeff_rows = 0;
    r->coeff_width = -1;
    while ((more = next_element(c, &started)) == 1) {
        if (tok(c) == '[') {
            int row_started = 0, width = 0, m;
            if (r->coeff_rows < 0) {
                return fail(c, CE_ERR_FIELD);
            }
            if (r->coeff_rows == CE_MAX_SEGMENTS) {
                return fail(c, CE_ERR_LIMIT);
            }
            while ((m = next_element(c, &row_started)) == 1) {
                double d;
                if (width == CE_MAX_COEFFS) {
                    return fail(c, CE_ERR_LIMIT);
                }
                if (number_value(c, &d)) {
                    return c->err;
                }
                CE_ASSERT(r->coeff_rows < CE_MAX_SEGMENTS && width < CE_MAX_COEFFS);
                r->matrix[r->coeff_rows][width++] = d;
            }
            if (m < 0) {
                return m;
            }
            if (width == 0 || (r->coeff_width >= 0 && width != r->coeff_width)) {
                return fail(c, CE_ERR_FIELD);
            }
            r->coeff_width = width;
            r->coeff_rows++;
        } else {
            double d;
            if (r->coeff_rows > 0) {
                return fail(c, CE_ERR_FIELD);
            }
            if (r->coeff_width == CE_MAX_COEFFS) {
                return fail(c, CE_ERR_LIMIT);
            }
            if (number_value(c, &d)) {
                return c->err;
            }
            r->coeff_rows = -1;
            r->coeff_width = r->coeff_width < 0 ? 1 : r->coeff_width + 1;
            r->flat[r->coeff_width - 1] = d;
        }
    }
    return more;
}

/* A field only the other model kind has ("kind" sorts before all of them): canical does not
 * read it, so neither does the device. */
static int other_kinds_field(const members *it, int kind)
{
    int piecewise_only = key_is(it, "knots_raw") || key_is(it, "scale") || key_is(it, "smoothness");
    int forward_only = key_is(it, "rate_scale") || key_is(it, "rate_span_dps");
    return (kind == KIND_FORWARD && piecewise_only) ||
           ((kind == KIND_SEG_INVERSE || kind == KIND_SEG_LINEAR) && forward_only);
}

static int parse_model(cur *c, reading *r)
{
    members it = {NULL, 0, 0};
    int more;
    r->have_model = 1;
    while ((more = next_member(c, &it)) == 1) {
        int n;
        if (key_is(&it, "coefficients")) {
            if (parse_coefficients(c, r)) {
                return c->err;
            }
        } else if (key_is(&it, "kind")) {
            const uint8_t *s;
            uint32_t len;
            if (string_value(c, &s, &len)) {
                return c->err;
            }
            r->kind = bytes_are(s, len, "segmented-inverse") ? KIND_SEG_INVERSE
                      : bytes_are(s, len, "segmented-linear") ? KIND_SEG_LINEAR
                      : bytes_are(s, len, "forward-poly")     ? KIND_FORWARD
                                                              : KIND_NONE;
            if (r->kind == KIND_NONE) {
                return fail(c, CE_ERR_MODEL_KIND);
            }
        } else if (other_kinds_field(&it, r->kind)) {
            if (skip_value(c)) {
                return c->err;
            }
        } else if (key_is(&it, "knots_raw")) {
            r->have_knots = 1;
            if (number_list(c, r->knots, CE_MAX_SEGMENTS - 1, &r->n_knots)) {
                return c->err;
            }
        } else if (key_is(&it, "span_raw") || key_is(&it, "rate_span_dps")) {
            double two[3];
            int span = key_is(&it, "span_raw");
            if (number_list(c, two, 3, &n)) {
                return c->err;
            }
            if (n != 2) {
                return fail(c, CE_ERR_FIELD);
            }
            if (span) {
                r->have_span = 1;
                r->span[0] = two[0];
                r->span[1] = two[1];
            } else {
                r->have_rate_span = 1;
                r->rate_span[0] = two[0];
                r->rate_span[1] = two[1];
            }
        } else if (key_is(&it, "scale")) {
            r->have_scale = 1;
            if (number_value(c, &r->scale)) {
                return c->err;
            }
        } else if (key_is(&it, "rate_scale")) {
            r->have_rate_scale = 1;
            if (number_value(c, &r->rate_scale)) {
                return c->err;
            }
        } else if (key_is(&it, "smoothness")) {
            int b = tok(c);
            double d;
            if (b == 'n' || b == 't' || b == 'f') {
                if (parse_scalar(c)) {
                    return c->err;
                }
            } else if (number_value(c, &d)) {
                return c->err;
            } else if (!(d == 0.0 || d == 1.0)) {
                return fail(c, CE_ERR_FIELD);
            }
        } else if (key_is(&it, "segment_points_dps")) {
            int started = 0, m;
            while ((m = next_element(c, &started)) == 1) {
                double d;
                if (number_value(c, &d)) {
                    return c->err;
                }
            }
            if (m < 0) {
                return m;
            }
        } else if (skip_value(c)) {
            return c->err; /* out_of_span and anything newer: not needed to evaluate */
        }
    }
    return more;
}

/* A term's fields as read, before they are checked against its kind. */
typedef struct {
    const uint8_t *kind, *feature, *form;
    uint32_t kind_n, feature_n, form_n;
    double coefficient, reference, tau, threshold;
    int have_coefficient, have_reference, have_tau, have_threshold;
    int channel_ok; /* a non-empty channel name */
    int have_knots, have_pieces, n_rows; /* a spline's, read into the set's next spline slot */
} term_fields;

/* A name (kind, feature, form): its bytes if it is a string; any other value is skipped and the
 * name left NULL, refused later as an unknown kind, feature or form. */
static int name_value(cur *c, const uint8_t **s, uint32_t *n)
{
    *s = NULL;
    *n = 0;
    if (tok(c) == '"') {
        return string_value(c, s, n);
    }
    return skip_value(c);
}

/* The channel's name into the term's slot of `r` (channel names are matched after parsing). */
static int channel_value(cur *c, reading *r, uint8_t slot, term_fields *f)
{
    if (tok(c) != '"') {
        return skip_value(c);
    }
    if (string_value(c, &r->channel[slot], &r->channel_n[slot])) {
        return c->err;
    }
    f->channel_ok = r->channel_n[slot] > 0;
    return 0;
}

/* The evaluator's entry for the term's (kind, feature), or NULL when it has none. */
static const term_spec *find_term_spec(const term_fields *f)
{
    const term_spec *spec = NULL;
    size_t i;
    for (i = 0; i < N_TERM_SPECS; i++) {
        if (bytes_are(f->kind, f->kind_n, TERM_SPECS[i].kind) &&
            bytes_are(f->feature, f->feature_n, TERM_SPECS[i].feature)) {
            spec = &TERM_SPECS[i];
        }
    }
    return spec;
}

/* A spline knot as a float pair. A knot within a few double ulps of a float32 number (2^-50 of
 * it) is that number (lo = 0): canical writes a float32 knot (a channel value as the device
 * sees it) with 17 digits, which parse_number reads to within an ulp or two, and a sample
 * exactly on such a knot must fall in the segment above it, as in canical. */
static void split_knot(double d, float *hi, float *lo)
{
    split(d, hi, lo);
    if ((double)*lo <= 0x1p-50 * (d < 0.0 ? -d : d) && (double)*lo >= -0x1p-50 * (d < 0.0 ? -d : d)) {
        *lo = 0.0f;
    }
}

/* A spline's knots into `sp`: 2..CE_MAX_SPLINE_KNOTS finite numbers, strictly increasing (more
 * knots: CE_ERR_LIMIT), each within float range, kept as float pairs. */
static int parse_knots(cur *c, ce_spline *sp, term_fields *f)
{
    int started = 0, more;
    double prev = 0.0;
    sp->n_knots = 0;
    while ((more = next_element(c, &started)) == 1) {
        double d;
        int n = sp->n_knots;
        if (n == CE_MAX_SPLINE_KNOTS) {
            return fail(c, CE_ERR_LIMIT);
        }
        if (number_value(c, &d)) {
            return c->err;
        }
        if (n > 0 && !(d > prev)) {
            return fail(c, CE_ERR_FIELD);
        }
        if (!(d >= -FLT_MAX && d <= FLT_MAX) || (n > 0 && !(d - prev <= FLT_MAX))) {
            return fail(c, CE_ERR_LIMIT); /* a float32 device cannot hold it */
        }
        CE_ASSERT(n < CE_MAX_SPLINE_KNOTS);
        split_knot(d, &sp->knot_hi[n], &sp->knot_lo[n]);
        if (n > 0) {
            sp->top_u = (float)(d - prev); /* the last segment's width, once the list ends */
        }
        prev = d;
        sp->n_knots = (uint8_t)(n + 1);
    }
    if (more < 0) {
        return more;
    }
    if (sp->n_knots < 2) {
        return fail(c, CE_ERR_FIELD);
    }
    f->have_knots = 1;
    return 0;
}

/* A spline's pieces into `sp`: one row of 4 finite numbers (a0 a1 a2 a3) per segment of the knots
 * read before them ("knots" sorts before "pieces"), each within float range. */
static int parse_pieces(cur *c, ce_spline *sp, term_fields *f)
{
    int started = 0, more;
    f->n_rows = 0;
    if (!f->have_knots) {
        return fail(c, CE_ERR_FIELD); /* pieces without knots */
    }
    while ((more = next_element(c, &started)) == 1) {
        int row_started = 0, width = 0, m;
        if (f->n_rows == sp->n_knots - 1) {
            return fail(c, CE_ERR_FIELD); /* more rows than segments */
        }
        while ((m = next_element(c, &row_started)) == 1) {
            double d;
            if (width == 4) {
                return fail(c, CE_ERR_FIELD);
            }
            if (number_value(c, &d)) {
                return c->err;
            }
            if (!(d >= -FLT_MAX && d <= FLT_MAX)) {
                return fail(c, CE_ERR_LIMIT);
            }
            CE_ASSERT(f->n_rows < CE_MAX_SPLINE_KNOTS - 1);
            sp->pieces[f->n_rows][width++] = (float)d;
        }
        if (m < 0) {
            return m;
        }
        if (width != 4) {
            return fail(c, CE_ERR_FIELD);
        }
        f->n_rows++;
    }
    if (more < 0) {
        return more;
    }
    f->have_pieces = 1;
    return 0;
}

/* A term's "knots" or "pieces": into the set's next free spline slot when the term's kind (read
 * before them: "feature" and "kind" sort first) carries a spline; skipped otherwise, as canical
 * ignores them there. A set with more spline terms than CE_MAX_SPLINES: CE_ERR_LIMIT. */
static int spline_field(cur *c, ce_set *set, term_fields *f, int knots)
{
    const term_spec *spec = find_term_spec(f);
    if (spec == NULL || !(spec->needs & NEEDS_SPLINE)) {
        return skip_value(c);
    }
    if (set->n_splines == CE_MAX_SPLINES) {
        return fail(c, CE_ERR_LIMIT);
    }
    CE_ASSERT(set->n_splines < CE_MAX_SPLINES);
    return knots ? parse_knots(c, &set->splines[set->n_splines], f)
                 : parse_pieces(c, &set->splines[set->n_splines], f);
}

/* Every member of a term object; unknown members are skipped. */
static int read_term_fields(cur *c, reading *r, ce_set *set, uint8_t slot, term_fields *f)
{
    members it = {NULL, 0, 0};
    int more, bad;
    while ((more = next_member(c, &it)) == 1) {
        if (key_is(&it, "channel")) {
            bad = channel_value(c, r, slot, f);
        } else if (key_is(&it, "coefficient")) {
            bad = optional_number(c, &f->coefficient, &f->have_coefficient);
        } else if (key_is(&it, "feature")) {
            bad = name_value(c, &f->feature, &f->feature_n);
        } else if (key_is(&it, "form")) {
            bad = name_value(c, &f->form, &f->form_n);
        } else if (key_is(&it, "kind")) {
            bad = name_value(c, &f->kind, &f->kind_n);
        } else if (key_is(&it, "knots") || key_is(&it, "pieces")) {
            bad = spline_field(c, set, f, key_is(&it, "knots"));
        } else if (key_is(&it, "reference")) {
            bad = optional_number(c, &f->reference, &f->have_reference);
        } else if (key_is(&it, "tau_s")) {
            bad = optional_number(c, &f->tau, &f->have_tau);
        } else if (key_is(&it, "threshold_raw")) {
            bad = optional_number(c, &f->threshold, &f->have_threshold);
        } else {
            bad = skip_value(c);
        }
        if (bad) {
            return c->err;
        }
    }
    return more < 0 ? more : 0;
}

/* 1 when the term has every field its kind needs, each in range, and a known form; a spline's
 * knots and pieces (one row per segment) were checked as they were read into `spline`. */
static int term_fields_ok(const term_spec *spec, const term_fields *f, const ce_spline *spline)
{
    if (!bytes_are(f->form, f->form_n, "bias") && !bytes_are(f->form, f->form_n, "scale")) {
        return 0;
    }
    if ((spec->needs & NEEDS_SPLINE) &&
        !(f->have_knots && f->have_pieces && f->n_rows == (int)spline->n_knots - 1)) {
        return 0;
    }
    return !(((spec->needs & NEEDS_CHANNEL) && !f->channel_ok) || !f->have_coefficient ||
             ((spec->needs & NEEDS_TAU) && !f->have_tau) ||
             ((spec->needs & NEEDS_THRESHOLD) && !f->have_threshold) ||
             (f->have_tau && !(f->tau >= CE_MIN_TAU_S && f->tau <= CE_MAX_TAU_S)) ||
             (f->have_threshold && !(f->threshold > 0.0)));
}

/* The evaluator's form of a checked term (its state starts at zero: the set was zeroed). */
static void fill_term(ce_term *t, const term_spec *spec, const term_fields *f)
{
    t->feature = spec->code;
    t->scale_form = (uint8_t)bytes_are(f->form, f->form_n, "scale");
    t->coefficient = (float)f->coefficient;
    t->reference = (float)f->reference;
    t->inv_tau = f->have_tau ? (float)(1.0 / f->tau) : 0.0f;
    t->threshold = f->have_threshold ? (float)f->threshold : 1.0f;
    if (f->have_tau) { /* the running mean lasts while elapsed ms < tau * 1000 (int32 ms) */
        double ms = f->tau * 1000.0;
        int32_t whole = ms < 2147483647.0 ? (int32_t)ms : INT32_MAX;
        t->mean_ms = whole < INT32_MAX && (double)whole < ms ? whole + 1 : whole;
    }
}

static int parse_term(cur *c, reading *r, ce_set *set, ce_term *t)
{
    term_fields f;
    const term_spec *spec;
    int err;
    uint8_t slot = (uint8_t)r->n_terms;
    CE_ASSERT(r->n_terms < CE_MAX_TERMS);
    zero(&f, sizeof f);
    r->channel[slot] = NULL;
    r->channel_n[slot] = 0;
    err = read_term_fields(c, r, set, slot, &f);
    if (err) {
        return err;
    }
    spec = find_term_spec(&f);
    if (spec == NULL) {
        return fail(c, CE_ERR_TERM_KIND);
    }
    if (set->n_splines == CE_MAX_SPLINES && (spec->needs & NEEDS_SPLINE)) {
        return fail(c, CE_ERR_FIELD); /* no knots read (beyond the slots they meet CE_ERR_LIMIT) */
    }
    if (!term_fields_ok(spec, &f, &set->splines[set->n_splines < CE_MAX_SPLINES ? set->n_splines : 0])) {
        return fail(c, CE_ERR_FIELD);
    }
    if (!(spec->needs & NEEDS_CHANNEL)) {
        r->channel[slot] = NULL; /* only channel terms read a named input */
    }
    fill_term(t, spec, &f);
    if (spec->needs & NEEDS_SPLINE) {
        t->spline = set->n_splines++; /* the slot its knots and pieces were read into */
    }
    return 0;
}

static int parse_terms(cur *c, reading *r, ce_set *set)
{
    int started = 0, more;
    while ((more = next_element(c, &started)) == 1) {
        if (r->n_terms == CE_MAX_TERMS) {
            return fail(c, CE_ERR_LIMIT);
        }
        if (tok(c) != '{') {
            return fail(c, c->err ? c->err : CE_ERR_FIELD);
        }
        if (parse_term(c, r, set, &set->terms[r->n_terms])) {
            return c->err;
        }
        r->n_terms++;
    }
    return more;
}

static int parse_sensor(cur *c, reading *r)
{
    members it = {NULL, 0, 0};
    int more;
    r->have_sensor = 1;
    while ((more = next_member(c, &it)) == 1) {
        if (key_is(&it, "axis") || key_is(&it, "id")) {
            const uint8_t *s;
            uint32_t n;
            if (string_value(c, &s, &n)) {
                return c->err;
            }
            if (key_is(&it, "axis")) {
                r->sensor_axis = s;
                r->sensor_axis_n = n;
            } else {
                r->sensor_id = s;
                r->sensor_id_n = n;
            }
        } else if (skip_value(c)) {
            return c->err;
        }
    }
    return more;
}

static int parse_top(cur *c, reading *r, ce_set *set)
{
    members it = {NULL, 0, 0};
    int more;
    while ((more = next_member(c, &it)) == 1) {
        if (key_is(&it, "crc32")) {
            return fail(c, CE_ERR_NOT_CANONICAL); /* the CRC is never part of what it covers */
        } else if (key_is(&it, "fit") || key_is(&it, "units")) {
            if (tok(c) != '{') {
                return fail(c, c->err ? c->err : CE_ERR_FIELD);
            }
            r->have_units |= key_is(&it, "units");
            if (skip_value(c)) {
                return c->err;
            }
        } else if (key_is(&it, "model")) {
            if (parse_model(c, r)) {
                return c->err;
            }
        } else if (key_is(&it, "schema")) {
            int b = tok(c);
            double d = 0.0;
            r->have_schema = 1;
            if (b == '-' || is_digit(b)) {
                if (parse_number(c, &d)) {
                    return c->err;
                }
                r->schema_ok = d == 1.0;
            } else if (skip_value(c)) {
                return c->err;
            }
        } else if (key_is(&it, "sensor")) {
            if (parse_sensor(c, r)) {
                return c->err;
            }
        } else if (key_is(&it, "terms")) {
            if (parse_terms(c, r, set)) {
                return c->err;
            }
        } else if (key_is(&it, "v0")) {
            r->have_v0 = 1;
            if (number_value(c, &r->v0)) {
                return c->err;
            }
        } else if (skip_value(c)) {
            return c->err; /* created, and keys a newer schema may add */
        }
    }
    if (more < 0) {
        return more;
    }
    if (c->p != c->end) {
        return fail(c, CE_ERR_SYNTAX); /* trailing bytes */
    }
    return 0;
}

/* ------------------------------------------------------------------------------------------
 * Evaluation.
 * ---------------------------------------------------------------------------------------- */

/* raw - shift >= k_hi + k_lo, decided to about 2^-48 of the values (raw and k_hi are close
 * whenever the answer is close, so raw - k_hi is exact). */
static int at_or_above(float raw, float shift, float k_hi, float k_lo)
{
    return (raw - k_hi) - shift >= k_lo;
}

static float horner(const float *c, int n, float u)
{
    float acc;
    int k;
    CE_ASSERT(n >= 1 && n <= CE_MAX_COEFFS);
    acc = c[n - 1];
    for (k = n - 2; k >= 0; k--) {
        acc = acc * u + c[k];
    }
    return acc;
}

/* d/du of the polynomial. */
static float horner_slope(const float *c, int n, float u)
{
    float acc;
    int k;
    if (n < 2) {
        return 0.0f;
    }
    acc = (float)(n - 1) * c[n - 1];
    for (k = n - 2; k >= 1; k--) {
        acc = acc * u + (float)k * c[k];
    }
    return acc;
}

/* Forward polynomial: the rate w with f(w) = target by safeguarded Newton from the chord,
 * then linear beyond the span (dv - target). */
static float forward_rate(const ce_set *s, float target, float dv)
{
    const float *c = s->coeffs[0];
    int n = s->n_coeffs, i, k;
    float w = s->w_lo + (target - s->chord_dv) * s->chord_slope;
    float slope = 0.0f;
    for (i = 0; i < CE_NEWTON_MAX_ITER; i++) {
        float u = w * s->inv_scale, f = c[n - 1], df = 0.0f, step;
        for (k = n - 2; k >= 0; k--) {
            df = df * u + f;
            f = f * u + c[k];
        }
        slope = df * s->inv_scale;
        if (!(slope != 0.0f)) {
            break;
        }
        step = (f - target) / slope;
        w -= step;
        w = w < s->w_lo ? s->w_lo : w > s->w_hi ? s->w_hi : w;
        if (absf(step) < s->newton_tol) {
            break;
        }
    }
    if (dv != target) {
        slope = horner_slope(c, n, w * s->inv_scale) * s->inv_scale;
        return w + (dv - target) / slope;
    }
    return w;
}

/* Hysteresis on v (canical.sets.terms.DirectionTracker): +1/-1 after a move larger than the
 * threshold from the last extreme, 0 before either. */
static float hysteresis(ce_term *t, float v)
{
    if (!t->started) {
        t->started = 1;
        t->high = t->low = v;
        t->state = 0.0f;
    }
    if (v > t->high) {
        t->high = v;
    }
    if (v < t->low) {
        t->low = v;
    }
    if (t->state <= 0.0f && v - t->low > t->threshold) {
        t->state = 1.0f;
        t->high = v;
    } else if (t->state >= 0.0f && t->high - v > t->threshold) {
        t->state = -1.0f;
        t->low = v;
    }
    return t->state;
}

/* hi + lo += d, exactly to about 2^-48 of hi (TwoSum, then renormalise). */
static void pair_add(float *hi, float *lo, float d)
{
    float s = *hi + d;
    float bb = s - *hi;
    float err = (*hi - (s - bb)) + (d - bb);
    float l = *lo + err;
    *hi = s + l;
    *lo = l - (*hi - s);
}

/* v minus the first-order lag y of channel v (canical.sets.terms.ChannelTracker): for the first tau
 * of the stream y is the running mean of the samples, then y += (1 - exp(-dt/tau)) (v - y),
 * exact for any spacing; a sample whose time does not advance leaves y alone. y is a float
 * pair: with a long tau the steps are far below y's float32 resolution. */
static float channel_lag_gap(ce_term *t, float v, uint32_t now_ms)
{
    if (!t->started) {
        t->started = 1;
        t->lagging = 0;
        t->y = v;
        t->y_err = 0.0f;
        t->start_ms = now_ms;
        t->count = 1u;
    } else if (!t->lagging && (int32_t)(now_ms - t->start_ms) < t->mean_ms) {
        if (t->count < 0xFFFFFFFFu) {
            t->count++;
        }
        pair_add(&t->y, &t->y_err, ((v - t->y) - t->y_err) / (float)t->count);
    } else {
        t->lagging = 1; /* time runs forward: the mean never resumes (not even after the ms wrap) */
        if ((int32_t)(now_ms - t->last_ms) > 0) {
            float dt = (float)(now_ms - t->last_ms) * 0.001f;
            pair_add(&t->y, &t->y_err, -expm1_f(-dt * t->inv_tau) * ((v - t->y) - t->y_err));
        }
    }
    t->last_ms = now_ms;
    return (v - t->y) - t->y_err;
}

/* S(var) of a spline (canical.sets.term_kinds.spline_one), the same steps in the same order:
 * var clamped to [b_0, b_m]; the segment i, the last knot at or below it (binary search: at
 * most log2(CE_MAX_SPLINE_KNOTS) steps); Horner in u = var - b_i. The knot comparisons and u
 * use the knots' float pairs, so the segment is the one double precision chooses. A NaN var
 * gives NaN, as in canical. */
static float spline_at(const ce_spline *sp, float var)
{
    int last = sp->n_knots - 2, lo = 0, hi;
    const float *a;
    float u;
    CE_ASSERT(sp->n_knots >= 2 && sp->n_knots <= CE_MAX_SPLINE_KNOTS);
    if ((var - sp->knot_hi[0]) < sp->knot_lo[0]) {
        u = 0.0f; /* below b_0: w = b_0, segment 0 */
    } else if ((var - sp->knot_hi[last + 1]) > sp->knot_lo[last + 1]) {
        lo = last; /* above b_m: w = b_m, the last segment */
        u = sp->top_u;
    } else {
        hi = last;
        while (lo < hi) {
            int mid = (lo + hi + 1) / 2;
            if ((var - sp->knot_hi[mid]) >= sp->knot_lo[mid]) {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        u = (var - sp->knot_hi[lo]) - sp->knot_lo[lo];
    }
    CE_ASSERT(lo >= 0 && lo <= last);
    a = sp->pieces[lo];
    return ((a[3] * u + a[2]) * u + a[1]) * u + a[0];
}

static float term_feature(ce_term *t, const ce_spline *splines, const ce_sample *in, float t_s, float dv)
{
    float x;
    switch (t->feature) {
    case CE_TERM_CHANNEL_SPLINE: /* S(v) */
        return spline_at(&splines[t->spline], in->inputs[t->input]);
    case CE_TERM_CHANNEL_RATE_SPLINE: /* (v - ref) R(dV); R's knots are raw counts: compared with raw */
        return (in->inputs[t->input] - t->reference) * spline_at(&splines[t->spline], in->raw);
    case CE_TERM_CHANNEL_LAG_SPLINE: /* S(y): the lag's steps, then its float pair y rounded once */
        (void)channel_lag_gap(t, in->inputs[t->input], in->time_ms);
        return spline_at(&splines[t->spline], t->y + t->y_err);
    case CE_TERM_CHANNEL_DERIVATIVE_SPLINE: /* S((v - y) / tau) */
        return spline_at(&splines[t->spline], channel_lag_gap(t, in->inputs[t->input], in->time_ms) * t->inv_tau);
    case CE_TERM_CHANNEL_GATED: /* (v - ref) * max(|dv| - knee, 0) / max(|dv|, knee) */
        x = dv < 0.0f ? -dv : dv;
        return x > t->threshold ? (in->inputs[t->input] - t->reference) * ((x - t->threshold) / x) : 0.0f;
    case CE_TERM_CHANNEL_OFFSET:
        return in->inputs[t->input] - t->reference;
    case CE_TERM_CHANNEL_SQUARE:
        x = in->inputs[t->input] - t->reference;
        return x * x;
    case CE_TERM_CHANNEL_LAG: /* y - ref = v - ref - (v - y) */
        x = in->inputs[t->input];
        return (x - t->reference) - channel_lag_gap(t, x, in->time_ms);
    case CE_TERM_CHANNEL_DERIVATIVE: /* dy/dt = (v - y) / tau */
        return channel_lag_gap(t, in->inputs[t->input], in->time_ms) * t->inv_tau;
    case CE_TERM_CHANNEL_DIRECTION:
        return hysteresis(t, in->inputs[t->input]);
    case CE_TERM_TIME_WARMUP:
        return -expm1_f(-t_s * t->inv_tau);
    case CE_TERM_TIME_LINEAR:
        return t_s;
    case CE_TERM_DIRECTION_SIGN: /* hysteresis on the raw output */
        return hysteresis(t, in->raw);
    case CE_TERM_DIRECTION_SLOPE: /* d(raw)/dt smoothed with time constant tau */
        if (t->started && (int32_t)(in->time_ms - t->last_ms) > 0) {
            float dt = (float)(in->time_ms - t->last_ms) * 0.001f;
            float alpha = -expm1_f(-dt * t->inv_tau);
            t->state += alpha * ((in->raw - t->last_raw) / dt - t->state);
        }
        t->started = 1;
        t->last_raw = in->raw;
        t->last_ms = in->time_ms;
        return t->state;
    default:
        return 0.0f; /* unreachable: ce_load refuses codes it does not know */
    }
}

int ce_eval(ce_set *s, const ce_sample *in, float *rate_dps)
{
    float raw, dv, shift = 0.0f, x, t_s;
    int seg = 0, oos = 0, i, last;
    if (s == NULL || in == NULL || rate_dps == NULL || !s->loaded || (s->needs_inputs && in->inputs == NULL)) {
        return CE_ERR_ARG;
    }
    raw = in->raw;
    dv = (raw - s->v0_hi) - s->v0_lo;
    t_s = (float)in->time_ms * 0.001f;
    for (i = 0; i < s->n_terms; i++) {
        ce_term *t = &s->terms[i];
        float f = term_feature(t, s->splines, in, t_s, dv);
        shift += t->coefficient * (t->scale_form ? f * dv : f);
    }
    if (!at_or_above(raw, shift, s->lo_hi, s->lo_lo)) {
        oos = 1;
        x = s->dv_lo;
    } else if ((raw - s->hi_hi) - shift > s->hi_lo) {
        oos = 1;
        x = s->dv_hi;
        seg = s->n_segments - 1;
    } else {
        x = dv - shift;
        last = s->n_segments - 1;
        while (seg < last && at_or_above(raw, shift, s->knot_hi[seg], s->knot_lo[seg])) {
            seg++;
        }
    }
    CE_ASSERT(s->n_segments >= 1 && s->n_segments <= CE_MAX_SEGMENTS && seg >= 0 && seg < s->n_segments);
    dv -= shift;
    if (s->model == 1) {
        *rate_dps = forward_rate(s, x, dv);
        return oos;
    }
    {
        /* the segment's polynomial about its centre: t = (dV - mid) / half-width, |t| <= 1 */
        const float *c = s->coeffs[seg];
        float t = (x - s->seg_mid[seg]) * s->seg_inv_half[seg];
        float rate = horner(c, s->n_coeffs, t);
        if (oos) {
            rate += horner_slope(c, s->n_coeffs, t) * s->seg_inv_half[seg] * (dv - x);
        }
        *rate_dps = rate;
    }
    return oos;
}

int ce_eval_block(ce_set *set, uint32_t n, const float *raw, const uint32_t *time_ms, const float *inputs,
                  uint8_t n_inputs, float *rate_dps, uint8_t *out_of_span)
{
    uint32_t i;
    if (set == NULL || raw == NULL || rate_dps == NULL || out_of_span == NULL || !set->loaded) {
        return CE_ERR_ARG;
    }
    for (i = 0; i < n; i++) {
        ce_sample sample;
        int r;
        sample.raw = raw[i];
        sample.time_ms = time_ms != NULL ? time_ms[i] : 0u;
        sample.inputs = inputs != NULL ? inputs + (size_t)i * n_inputs : NULL;
        r = ce_eval(set, &sample, &rate_dps[i]);
        if (r < 0) {
            return r;
        }
        out_of_span[i] = (uint8_t)r;
    }
    return CE_OK;
}

void ce_reset(ce_set *set)
{
    int i;
    if (set == NULL) {
        return;
    }
    for (i = 0; i < CE_MAX_TERMS; i++) {
        set->terms[i].started = 0;
        set->terms[i].state = 0.0f;
    }
}

/* ------------------------------------------------------------------------------------------
 * Loading: parse, check every field, admit for the device, derive the run-time form.
 * ---------------------------------------------------------------------------------------- */

static double horner_d(const double *c, int n, double u)
{
    double acc = c[n - 1];
    int k;
    for (k = n - 2; k >= 0; k--) {
        acc = acc * u + c[k];
    }
    return acc;
}

/* canical.sets.finite_outputs.forward_bound for a set without terms: 1 when the forward
 * polynomial's slope is finite and of one sign at 512 points across the rate span (as numpy's
 * linspace places them), sum |a_k| u^k stays within 1e150 (u the largest |rate| / rate_scale),
 * and the rate extrapolated 2^33 counts beyond the span by the edge slope stays within 1e150: a
 * polynomial without an inverse, or whose outputs overflow, is refused as canical refuses it. */
static int forward_invertible(const reading *r, double lo, double hi)
{
    const double limit = 1e150, reach_raw = 8589934592.0; /* RATE_LIMIT_DPS, RAW_REACH = 2^33 */
    double a = r->rate_span[0], b = r->rate_span[1], step = (b - a) / 511.0;
    double u_max = (a < 0.0 ? -a : a) > (b < 0.0 ? -b : b) ? (a < 0.0 ? -a : a) : (b < 0.0 ? -b : b);
    double sum = 0.0, power = 1.0, first = 0.0, last = 0.0, reach, edge;
    int i, k, n = r->coeff_width, positive = 0, negative = 0, zero = 0;
    for (k = 0; k < n; k++) {
        sum += (r->flat[k] < 0.0 ? -r->flat[k] : r->flat[k]) * power;
        power *= u_max / r->rate_scale;
    }
    if (!(sum <= limit)) {
        return 0;
    }
    for (i = 0; i < 512; i++) {
        double u = (i == 511 ? b : (double)i * step + a) / r->rate_scale, d = (double)(n - 1) * r->flat[n - 1];
        for (k = n - 2; k >= 1; k--) {
            d = d * u + (double)k * r->flat[k];
        }
        d /= r->rate_scale;
        if (!(d - d == 0.0)) {
            return 0;
        }
        positive |= d > 0.0;
        negative |= d < 0.0;
        zero |= d == 0.0;
        if (i == 0) {
            first = d < 0.0 ? -d : d;
        }
        last = d < 0.0 ? -d : d;
    }
    if (zero || positive == negative) {
        return 0; /* the slope changes sign or is zero somewhere: no inverse */
    }
    reach = lo - (r->span[0] - r->v0 - reach_raw);
    if ((r->span[1] - r->v0 + reach_raw) - hi > reach) {
        reach = (r->span[1] - r->v0 + reach_raw) - hi;
    }
    edge = first < last ? first : last;
    return u_max + (reach > 0.0 ? reach : 0.0) / edge <= limit;
}

static int serial_matches(uint32_t serial, const uint8_t *id, uint32_t n)
{
    char digits[10];
    int len = 0, i;
    do {
        digits[len++] = (char)('0' + serial % 10u);
        serial /= 10u;
    } while (serial != 0u);
    if (n != (uint32_t)len) {
        return 0;
    }
    for (i = 0; i < len; i++) {
        if (id[i] != (uint8_t)digits[len - 1 - i]) {
            return 0;
        }
    }
    return 1;
}

static int check_fields(const reading *r)
{
    int i;
    if (!r->have_schema || !r->schema_ok) {
        return CE_ERR_SCHEMA;
    }
    if (!r->have_sensor || !r->have_units || !r->have_model || !r->have_v0 || r->sensor_id_n == 0 ||
        r->sensor_axis_n == 0) {
        return CE_ERR_FIELD;
    }
    if (r->kind == KIND_NONE) {
        return CE_ERR_MODEL_KIND;
    }
    if (!r->have_span || !(r->span[0] < r->span[1]) || !r->have_coeffs) {
        return CE_ERR_FIELD;
    }
    if (r->kind == KIND_FORWARD) {
        if (r->coeff_rows != -1 || r->coeff_width < 2 || !r->have_rate_scale || !(r->rate_scale > 0.0) ||
            !r->have_rate_span || !(r->rate_span[0] < r->rate_span[1]) || r->n_terms > 0) {
            return CE_ERR_FIELD;
        }
        return CE_OK;
    }
    if (!r->have_knots || !r->have_scale || !(r->scale > 0.0) || r->coeff_rows != r->n_knots + 1) {
        return CE_ERR_FIELD;
    }
    for (i = 0; i < r->n_knots; i++) {
        if ((i > 0 && !(r->knots[i - 1] < r->knots[i])) || !(r->span[0] < r->knots[i] && r->knots[i] < r->span[1])) {
            return CE_ERR_FIELD;
        }
    }
    return CE_OK;
}

/* Lowest and highest rate at the span's edges, as canical.sets.admission.span_rates. */
static void span_rates(const ce_set *s, const reading *r, float *low, float *high)
{
    float a, b;
    if (s->model == 1) {
        float e0 = (float)(r->span[0] - r->v0), e1 = (float)(r->span[1] - r->v0);
        float t0 = e0 < s->dv_lo ? s->dv_lo : e0 > s->dv_hi ? s->dv_hi : e0;
        float t1 = e1 < s->dv_lo ? s->dv_lo : e1 > s->dv_hi ? s->dv_hi : e1;
        a = forward_rate(s, t0, e0);
        b = forward_rate(s, t1, e1);
    } else {
        int last = s->n_segments - 1;
        a = horner(s->coeffs[0], s->n_coeffs, (s->dv_lo - s->seg_mid[0]) * s->seg_inv_half[0]);
        b = horner(s->coeffs[last], s->n_coeffs, (s->dv_hi - s->seg_mid[last]) * s->seg_inv_half[last]);
    }
    *low = a < b ? a : b;
    *high = a < b ? b : a;
}

static int admit(ce_set *s, const reading *r, const ce_device *device)
{
    int i, j;
    float low, high;
    if (!serial_matches(device->serial, r->sensor_id, r->sensor_id_n)) {
        return CE_ERR_SENSOR;
    }
    if (r->sensor_axis_n != 1 || r->sensor_axis[0] != (uint8_t)device->axis) {
        return CE_ERR_AXIS;
    }
    for (i = 0; i < r->n_terms; i++) {
        if (r->channel[i] == NULL) {
            continue;
        }
        for (j = 0; j < device->n_inputs && j < CE_MAX_INPUTS; j++) {
            const char *name = device->inputs != NULL ? device->inputs[j] : NULL;
            if (name != NULL && bytes_are(r->channel[i], r->channel_n[i], name)) {
                break;
            }
        }
        if (j == device->n_inputs || j == CE_MAX_INPUTS) {
            return CE_ERR_INPUT;
        }
        s->terms[i].input = (uint8_t)j;
        s->needs_inputs = 1;
    }
    if (device->rated_range_dps > 0.0f) {
        span_rates(s, r, &low, &high);
        if (!(low <= -device->rated_range_dps && high >= device->rated_range_dps)) {
            return CE_ERR_SPAN;
        }
    }
    return CE_OK;
}

/* Segment `seg`'s polynomial p(u) = sum c[k] u^k, u = dV / scale, re-expressed about the
 * segment [a, b] (dV) as q(t) = sum s->coeffs[seg][k] t^k, t = (dV - mid) / half: the same
 * polynomial, but |t| <= 1 across the segment. Calibrated sets have large alternating c[k]
 * over wide segments (|u| up to ~1); summed in float32 they cancel to errors far above the
 * rate's own rounding, whereas the centred coefficients are about the size of the rate's
 * variation over the segment. The Taylor shift runs in double on the float32 mid and 1/half
 * actually stored, so the only per-sample error left is float32 rounding of small terms.
 * Should a coefficient not fit a float (never for a set whose span is reached), the
 * segment keeps the plain form (mid 0, half = scale), exactly as before this re-centring. */
static void recentre(ce_set *s, int seg, const double *c, int n, double scale, double a, double b)
{
    double d[CE_MAX_COEFFS], mid, half, shift, power = 1.0;
    float mid_f = (float)(0.5 * (a + b)), inv_half_f = (float)(2.0 / (b - a));
    int j, k, fits = 1;
    CE_ASSERT(seg >= 0 && seg < CE_MAX_SEGMENTS && n >= 1 && n <= CE_MAX_COEFFS);
    mid = (double)mid_f;
    half = 1.0 / (double)inv_half_f;
    shift = mid / scale; /* p(shift + v): repeated synthetic division, O(n^2), in place */
    for (j = 0; j < n; j++) {
        d[j] = c[j];
    }
    for (j = 0; j < n - 1; j++) {
        for (k = n - 2; k >= j; k--) {
            d[k] += shift * d[k + 1];
        }
    }
    for (j = 0; j < n; j++) { /* v = (half / scale) t */
        float f = (float)(d[j] * power);
        fits = fits && f - f == 0.0f;
        s->coeffs[seg][j] = f;
        power *= half / scale;
    }
    if (fits && inv_half_f - inv_half_f == 0.0f && inv_half_f > 0.0f) {
        s->seg_mid[seg] = mid_f;
        s->seg_inv_half[seg] = inv_half_f;
        return;
    }
    for (j = 0; j < n; j++) {
        s->coeffs[seg][j] = (float)c[j];
    }
    s->seg_mid[seg] = 0.0f;
    s->seg_inv_half[seg] = (float)(1.0 / scale);
}

/* The run-time form: float pairs in raw units for every decision, floats for the rest. */
static int derive(ce_set *s, const reading *r)
{
    int i, j;
    double lo, hi;
    split(r->v0, &s->v0_hi, &s->v0_lo);
    s->n_terms = (uint8_t)r->n_terms;
    if (r->kind == KIND_FORWARD) {
        double f_lo = horner_d(r->flat, r->coeff_width, r->rate_span[0] / r->rate_scale);
        double f_hi = horner_d(r->flat, r->coeff_width, r->rate_span[1] / r->rate_scale);
        if (!(f_lo != f_hi) || !(f_hi - f_lo == f_hi - f_lo)) {
            return CE_ERR_FIELD; /* flat over its rate span: no inverse */
        }
        s->model = 1;
        s->n_segments = 1;
        s->n_coeffs = (uint8_t)r->coeff_width;
        for (j = 0; j < r->coeff_width; j++) {
            s->coeffs[0][j] = (float)r->flat[j];
        }
        s->inv_scale = (float)(1.0 / r->rate_scale);
        s->w_lo = (float)r->rate_span[0];
        s->w_hi = (float)r->rate_span[1];
        s->chord_dv = (float)f_lo;
        s->chord_slope = (float)((r->rate_span[1] - r->rate_span[0]) / (f_hi - f_lo));
        s->newton_tol = (float)(1e-6 * (r->rate_span[1] - r->rate_span[0]));
        lo = f_lo < f_hi ? f_lo : f_hi;
        hi = f_lo < f_hi ? f_hi : f_lo;
        if (!forward_invertible(r, lo, hi)) {
            return CE_ERR_FIELD;
        }
    } else {
        s->model = 0;
        s->n_segments = (uint8_t)r->coeff_rows;
        s->n_coeffs = (uint8_t)r->coeff_width;
        s->inv_scale = (float)(1.0 / r->scale);
        lo = r->span[0] - r->v0;
        hi = r->span[1] - r->v0;
        for (i = 0; i < r->coeff_rows; i++) {
            /* the segment in dV: [span low or knot i-1, knot i or span high] (knots lie inside) */
            double a = i == 0 ? lo : r->knots[i - 1] - r->v0;
            double b = i == r->n_knots ? hi : r->knots[i] - r->v0;
            recentre(s, i, r->matrix[i], r->coeff_width, r->scale, a, b);
        }
        for (i = 0; i < r->n_knots; i++) {
            split(r->knots[i], &s->knot_hi[i], &s->knot_lo[i]);
        }
    }
    s->dv_lo = (float)lo;
    s->dv_hi = (float)hi;
    split(lo + r->v0, &s->lo_hi, &s->lo_lo);
    split(hi + r->v0, &s->hi_hi, &s->hi_lo);
    for (i = 0; i < s->n_terms; i++) {
        if (s->terms[i].feature == CE_TERM_CHANNEL_RATE_SPLINE) { /* knots in dV -> raw counts */
            ce_spline *sp = &s->splines[s->terms[i].spline];
            for (j = 0; j < sp->n_knots; j++) {
                split_knot((double)sp->knot_hi[j] + (double)sp->knot_lo[j] + r->v0, &sp->knot_hi[j],
                           &sp->knot_lo[j]);
            }
        }
    }
    return CE_OK;
}

/* More channels than CE_MAX_INPUTS (a function of a uint32_t: no "always false" at 255). */
static int beyond_inputs(uint32_t n) { return n > CE_MAX_INPUTS; }

int ce_load(ce_set *set, const uint8_t *content, uint32_t length, uint32_t declared_crc,
            const ce_device *device)
{
    cur c;
    reading r;
    int code;
    if (set == NULL) {
        return CE_ERR_ARG;
    }
    zero(set, sizeof *set);
    if (content == NULL || device == NULL || beyond_inputs(device->n_inputs)) {
        return CE_ERR_ARG;
    }
    if (ce_crc32(content, length) != declared_crc) {
        return CE_ERR_CRC;
    }
    zero(&r, sizeof r);
    r.kind = KIND_NONE;
    c.base = c.p = content;
    c.end = content + length;
    c.err = 0;
    c.err_at = 0;
    if (tok(&c) != '{') {
        fail(&c, CE_ERR_SYNTAX);
    } else {
        parse_top(&c, &r, set);
    }
    code = c.err;
    if (code == CE_OK) {
        code = check_fields(&r);
    }
    if (code == CE_OK) {
        code = derive(set, &r);
    }
    if (code == CE_OK) {
        code = admit(set, &r, device);
    }
    if (code != CE_OK) {
        uint32_t at = c.err ? c.err_at : length;
        zero(set, sizeof *set);
        set->error_at = at;
        return code;
    }
    set->crc = declared_crc;
    set->loaded = 1;
    ce_reset(set);
    return CE_OK;
}

/* ------------------------------------------------------------------------------------------
 * An IMU set's coupling: parse, check (canical.sets.imu_set.check_coupling), apply.
 * ---------------------------------------------------------------------------------------- */

typedef struct {
    double m[3][3];
    int have_matrix, have_kind, have_schema, schema_ok, kind_ok;
    const uint8_t *sensor_id;
    uint32_t sensor_id_n;
} coupling_reading;

static int parse_matrix(cur *c, coupling_reading *r)
{
    int started = 0, rows = 0, more;
    while ((more = next_element(c, &started)) == 1) {
        int count;
        if (rows == 3) {
            return fail(c, CE_ERR_FIELD);
        }
        if (number_list(c, r->m[rows], 3, &count)) {
            return c->err == CE_ERR_LIMIT ? (c->err = CE_ERR_FIELD) : c->err;
        }
        if (count != 3) {
            return fail(c, CE_ERR_FIELD);
        }
        rows++;
    }
    if (more < 0) {
        return more;
    }
    if (rows != 3) {
        return fail(c, CE_ERR_FIELD);
    }
    r->have_matrix = 1;
    return 0;
}

static int parse_coupling_top(cur *c, coupling_reading *r)
{
    members it = {NULL, 0, 0};
    int more;
    while ((more = next_member(c, &it)) == 1) {
        if (key_is(&it, "crc32")) {
            return fail(c, CE_ERR_NOT_CANONICAL);
        } else if (key_is(&it, "axes")) {
            return fail(c, CE_ERR_FIELD); /* the axes are in their own banks */
        } else if (key_is(&it, "coupling")) {
            members in = {NULL, 0, 0};
            int more_in;
            while ((more_in = next_member(c, &in)) == 1) {
                if (key_is(&in, "matrix")) {
                    if (parse_matrix(c, r)) {
                        return c->err;
                    }
                } else if (skip_value(c)) {
                    return c->err; /* applied_to, standard_errors */
                }
            }
            if (more_in < 0) {
                return more_in;
            }
        } else if (key_is(&it, "kind")) {
            const uint8_t *s;
            uint32_t n;
            if (string_value(c, &s, &n)) {
                return c->err;
            }
            r->have_kind = 1;
            r->kind_ok = bytes_are(s, n, "imu-set");
        } else if (key_is(&it, "schema")) {
            int b = tok(c);
            double d = 0.0;
            r->have_schema = 1;
            if (b == '-' || is_digit(b)) {
                if (parse_number(c, &d)) {
                    return c->err;
                }
                r->schema_ok = d == 1.0;
            } else if (skip_value(c)) {
                return c->err;
            }
        } else if (key_is(&it, "sensor")) {
            members in = {NULL, 0, 0};
            int more_in;
            while ((more_in = next_member(c, &in)) == 1) {
                if (key_is(&in, "id")) {
                    if (string_value(c, &r->sensor_id, &r->sensor_id_n)) {
                        return c->err;
                    }
                } else if (skip_value(c)) {
                    return c->err;
                }
            }
            if (more_in < 0) {
                return more_in;
            }
        } else if (skip_value(c)) {
            return c->err; /* created, fit */
        }
    }
    if (more < 0) {
        return more;
    }
    if (c->p != c->end) {
        return fail(c, CE_ERR_SYNTAX);
    }
    return 0;
}

/* Square root by Newton's method (no libm): x scaled into [0.25, 4) by powers of 4 first. */
static double sqrt_d(double x)
{
    double scale = 1.0, y;
    int i;
    if (!(x > 0.0)) {
        return 0.0;
    }
    while (x >= 4.0) {
        x *= 0.25;
        scale *= 2.0;
    }
    while (x < 0.25) {
        x *= 4.0;
        scale *= 0.5;
    }
    y = 1.0;
    for (i = 0; i < 8; i++) {
        y = 0.5 * (y + x / y);
    }
    return y * scale;
}

/* 2-norm condition number of M, squared: the eigenvalue ratio of the symmetric MᵀM, its
 * eigenvalues found by cyclic Jacobi rotations (load time only). Returns -1 for a singular M. */
static double condition_squared(const double m[3][3])
{
    double a[3][3];
    double lo, hi;
    int i, j, k, sweep;
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) {
            a[i][j] = m[0][i] * m[0][j] + m[1][i] * m[1][j] + m[2][i] * m[2][j];
        }
    }
    for (sweep = 0; sweep < 50; sweep++) {
        double off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        double diag = a[0][0] * a[0][0] + a[1][1] * a[1][1] + a[2][2] * a[2][2];
        if (off <= 1e-32 * diag) {
            break;
        }
        for (i = 0; i < 2; i++) {
            for (j = i + 1; j < 3; j++) {
                double theta, t, c, s;
                if (a[i][j] == 0.0) {
                    continue;
                }
                theta = (a[j][j] - a[i][i]) / (2.0 * a[i][j]);
                t = 1.0 / ((theta < 0.0 ? -theta : theta) + sqrt_d(theta * theta + 1.0));
                if (theta < 0.0) {
                    t = -t;
                }
                c = 1.0 / sqrt_d(t * t + 1.0);
                s = t * c;
                for (k = 0; k < 3; k++) { /* A <- A J: columns i and j */
                    double aki = a[k][i], akj = a[k][j];
                    a[k][i] = c * aki - s * akj;
                    a[k][j] = s * aki + c * akj;
                }
                for (k = 0; k < 3; k++) { /* A <- Jᵀ A: rows i and j */
                    double aik = a[i][k], ajk = a[j][k];
                    a[i][k] = c * aik - s * ajk;
                    a[j][k] = s * aik + c * ajk;
                }
            }
        }
    }
    lo = hi = a[0][0];
    for (i = 1; i < 3; i++) {
        lo = a[i][i] < lo ? a[i][i] : lo;
        hi = a[i][i] > hi ? a[i][i] : hi;
    }
    if (!(lo > 0.0) || !(hi - hi == 0.0)) {
        return -1.0;
    }
    return hi / lo;
}

static int check_coupling_matrix(const double m[3][3])
{
    double cond2;
    int i, j;
    for (i = 0; i < 3; i++) { /* written so that NaN fails too */
        if (!(m[i][i] >= CE_COUPLING_MIN_DIAGONAL && m[i][i] <= CE_COUPLING_MAX_DIAGONAL)) {
            return CE_ERR_COUPLING;
        }
    }
    cond2 = condition_squared(m);
    if (cond2 < 0.0 || cond2 > CE_COUPLING_MAX_CONDITION * CE_COUPLING_MAX_CONDITION) {
        return CE_ERR_COUPLING;
    }
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) {
            double v = m[i][j] < 0.0 ? -m[i][j] : m[i][j];
            if (i != j && v > CE_COUPLING_MAX_OFF_DIAGONAL) {
                return CE_ERR_COUPLING;
            }
        }
    }
    return CE_OK;
}

/* ------------------------------------------------------------------------------------------
 * Signed sets: the signed message built in the caller's scratch, verified by the caller's function.
 * ---------------------------------------------------------------------------------------- */

/* A growing message in a fixed buffer; `fits` turns 0 for good once a piece does not fit. */
typedef struct {
    uint8_t *at;
    uint32_t size, used;
    int fits;
} ce_message;

static void message_put(ce_message *m, const uint8_t *data, uint32_t length)
{
    uint32_t i;
    if (!m->fits || length > m->size - m->used) {
        m->fits = 0;
        return;
    }
    for (i = 0; i < length; i++) {
        m->at[m->used + i] = data[i];
    }
    m->used += length;
}

static void message_text(ce_message *m, const char *text)
{
    message_put(m, (const uint8_t *)text, (uint32_t)text_length(text));
}

/* An unsigned integer in decimal, as JSON writes it. */
static void message_decimal(ce_message *m, uint64_t value)
{
    uint8_t digits[20];
    uint32_t n = 0, i;
    uint8_t out[20];
    do {
        digits[n++] = (uint8_t)('0' + (uint8_t)(value % 10u));
        value /= 10u;
    } while (value != 0u);
    for (i = 0; i < n; i++) {
        out[i] = digits[n - 1u - i];
    }
    message_put(m, out, n);
}

static uint64_t read_u64_le(const uint8_t *p)
{
    uint64_t v = 0;
    int i;
    for (i = 7; i >= 0; i--) {
        v = (v << 8) | p[i];
    }
    return v;
}

/* The first checks, on the Signature's bytes alone: signed, its length, the key id. */
static int signature_header(const ce_trust *trust, const uint8_t *signature, uint32_t signature_length)
{
    int i;
    if (trust == NULL || trust->public_key == NULL || trust->key_id == NULL || trust->verify == NULL ||
        trust->scratch == NULL) {
        return CE_ERR_ARG;
    }
    if (signature_length == 0u) {
        return CE_ERR_UNSIGNED;
    }
    if (signature == NULL) {
        return CE_ERR_ARG;
    }
    if (signature_length != CE_SIGNATURE_BYTES) {
        return CE_ERR_SIGNATURE_FORMAT;
    }
    for (i = 0; i < CE_KEY_ID_BYTES; i++) {
        if (signature[8 + i] != trust->key_id[i]) {
            return CE_ERR_KEY;
        }
    }
    return CE_OK;
}

/* The domain and header of the signed message: "canical signed set v1\n" {"sensor":"S","version":N}\n. */
static ce_message message_start(const ce_trust *trust, uint32_t serial, uint64_t version)
{
    ce_message m;
    m.at = trust->scratch;
    m.size = trust->scratch_size;
    m.used = 0u;
    m.fits = 1;
    message_text(&m, "canical signed set v1\n{\"sensor\":\"");
    message_decimal(&m, serial);
    message_text(&m, "\",\"version\":");
    message_decimal(&m, version);
    message_text(&m, "}\n");
    return m;
}

/* The last checks, once the message is built: the signature, then the version. */
static int signature_verdict(const ce_trust *trust, const uint8_t *signature, const ce_message *m,
                             uint64_t *version)
{
    uint64_t v = read_u64_le(signature);
    if (!m->fits) {
        return CE_ERR_LIMIT;
    }
    if (trust->verify(trust->context, signature + 16, m->at, m->used, trust->public_key) != 0) {
        return CE_ERR_SIGNATURE;
    }
    if (v < trust->counter) {
        return CE_ERR_ROLLBACK;
    }
    *version = v;
    return CE_OK;
}

int ce_signature_check(const ce_trust *trust, const uint8_t *signature, uint32_t signature_length,
                       const uint8_t *content, uint32_t length, uint32_t serial, uint64_t *version)
{
    ce_message m;
    int code = signature_header(trust, signature, signature_length);
    if (code != CE_OK) {
        return code;
    }
    if (content == NULL || version == NULL) {
        return CE_ERR_ARG;
    }
    m = message_start(trust, serial, read_u64_le(signature));
    message_put(&m, content, length);
    return signature_verdict(trust, signature, &m, version);
}

int ce_signature_check3(const ce_trust *trust, const uint8_t *signature, uint32_t signature_length,
                        const uint8_t *content, uint32_t length, const uint8_t *const axis_content[3],
                        const uint32_t axis_length[3], uint32_t serial, uint64_t *version)
{
    static const char *const HEADS[3] = {"{\"axes\":{\"x\":", ",\"y\":", ",\"z\":"};
    ce_message m;
    int i;
    int code = signature_header(trust, signature, signature_length);
    if (code != CE_OK) {
        return code;
    }
    if (content == NULL || length < 2u || content[0] != '{' || axis_content == NULL || axis_length == NULL ||
        version == NULL) {
        return CE_ERR_ARG;
    }
    m = message_start(trust, serial, read_u64_le(signature));
    for (i = 0; i < 3; i++) {
        if (axis_content[i] == NULL) {
            return CE_ERR_ARG;
        }
        message_text(&m, HEADS[i]);
        message_put(&m, axis_content[i], axis_length[i]);
    }
    message_text(&m, "},");
    message_put(&m, content + 1, length - 1u);
    return signature_verdict(trust, signature, &m, version);
}

/* The IMU set's CRC32 from its axis banks and its coupling bank (see canical_eval.h). */
static uint32_t imu_set_crc(const uint8_t *const axis_content[3], const uint32_t axis_length[3],
                            const uint8_t *content, uint32_t length)
{
    static const char *const HEADS[3] = {"{\"axes\":{\"x\":", ",\"y\":", ",\"z\":"};
    uint32_t crc = 0xFFFFFFFFu;
    int i;
    for (i = 0; i < 3; i++) {
        crc = crc_text(crc, HEADS[i]);
        crc = crc_update(crc, axis_content[i], axis_length[i]);
    }
    crc = crc_text(crc, "},");
    return ~crc_update(crc, content + 1, length - 1);
}

int ce_coupling_load(ce_coupling *coupling, const uint8_t *content, uint32_t length, uint32_t declared_crc,
                     uint32_t imu_set_id, const uint8_t *const axis_content[3], const uint32_t axis_length[3],
                     const ce_device *device)
{
    cur c;
    coupling_reading r;
    int code, i, j;
    if (coupling == NULL) {
        return CE_ERR_ARG;
    }
    zero(coupling, sizeof *coupling);
    if (content == NULL || device == NULL || axis_content == NULL || axis_length == NULL) {
        return CE_ERR_ARG;
    }
    for (i = 0; i < 3; i++) {
        if (axis_content[i] == NULL) {
            return CE_ERR_ARG;
        }
    }
    if (ce_crc32(content, length) != declared_crc) {
        return CE_ERR_CRC;
    }
    zero(&r, sizeof r);
    c.base = c.p = content;
    c.end = content + length;
    c.err = 0;
    c.err_at = 0;
    if (tok(&c) != '{') {
        fail(&c, CE_ERR_SYNTAX);
    } else {
        parse_coupling_top(&c, &r);
    }
    code = c.err;
    if (code == CE_OK && !(r.have_schema && r.schema_ok)) {
        code = r.have_schema ? CE_ERR_SCHEMA : CE_ERR_FIELD;
    }
    if (code == CE_OK && !(r.have_kind && r.kind_ok && r.have_matrix && r.sensor_id != NULL)) {
        code = CE_ERR_FIELD;
    }
    if (code == CE_OK && !serial_matches(device->serial, r.sensor_id, r.sensor_id_n)) {
        code = CE_ERR_SENSOR;
    }
    if (code == CE_OK) {
        code = check_coupling_matrix((const double(*)[3])r.m);
    }
    if (code == CE_OK && imu_set_crc(axis_content, axis_length, content, length) != imu_set_id) {
        code = CE_ERR_IMU_SET;
    }
    if (code != CE_OK) {
        uint32_t at = c.err ? c.err_at : length;
        zero(coupling, sizeof *coupling);
        coupling->error_at = at;
        return code;
    }
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) {
            coupling->delta[i][j] = (float)(r.m[i][j] - (i == j ? 1.0 : 0.0));
        }
        coupling->axis_crc[i] = ce_crc32(axis_content[i], axis_length[i]);
    }
    coupling->crc = declared_crc;
    coupling->imu_set_id = imu_set_id;
    coupling->loaded = 1;
    return CE_OK;
}

int ce_eval3(ce_set *const axes[3], const ce_coupling *coupling, const ce_sample3 *sample, float rate_dps[3],
             uint8_t out_of_span[3])
{
    float r[3];
    int i;
    if (axes == NULL || sample == NULL || rate_dps == NULL || out_of_span == NULL) {
        return CE_ERR_ARG;
    }
    if (coupling != NULL) {
        if (!coupling->loaded) {
            return CE_ERR_ARG;
        }
        for (i = 0; i < 3; i++) {
            if (axes[i] == NULL || axes[i]->crc != coupling->axis_crc[i]) {
                return axes[i] == NULL ? CE_ERR_ARG : CE_ERR_IMU_SET;
            }
        }
    }
    for (i = 0; i < 3; i++) {
        ce_sample one;
        int code;
        one.raw = sample->raw[i];
        one.time_ms = sample->time_ms;
        one.inputs = sample->inputs;
        code = ce_eval(axes[i], &one, &r[i]);
        if (code < 0) {
            return code;
        }
        out_of_span[i] = (uint8_t)code;
    }
    if (coupling == NULL) {
        rate_dps[0] = r[0];
        rate_dps[1] = r[1];
        rate_dps[2] = r[2];
        return CE_OK;
    }
    for (i = 0; i < 3; i++) {
        const float *d = coupling->delta[i];
        rate_dps[i] = r[i] + (d[0] * r[0] + d[1] * r[1] + d[2] * r[2]);
    }
    return CE_OK;
}

int ce_eval3_block(ce_set *const axes[3], const ce_coupling *coupling, uint32_t n, const float *raw,
                   const uint32_t *time_ms, const float *inputs, uint8_t n_inputs, float *rate_dps,
                   uint8_t *out_of_span)
{
    uint32_t k;
    if (raw == NULL || rate_dps == NULL || out_of_span == NULL) {
        return CE_ERR_ARG;
    }
    for (k = 0; k < n; k++) {
        ce_sample3 s;
        int code;
        s.raw[0] = raw[3 * (size_t)k];
        s.raw[1] = raw[3 * (size_t)k + 1];
        s.raw[2] = raw[3 * (size_t)k + 2];
        s.time_ms = time_ms != NULL ? time_ms[k] : 0u;
        s.inputs = inputs != NULL ? inputs + (size_t)k * n_inputs : NULL;
        code = ce_eval3(axes, coupling, &s, rate_dps + 3 * (size_t)k, out_of_span + 3 * (size_t)k);
        if (code < 0) {
            return code;
        }
    }
    return CE_OK;
}

/* ------------------------------------------------------------------------------------------
 * Fixed point: integer decisions (raw counts are integers) and Q16/Q30 Horner in int64.
 * ---------------------------------------------------------------------------------------- */

static int64_t round_to_int(double d) { return (int64_t)(d < 0.0 ? d - 0.5 : d + 0.5); }

/* Smallest integer >= d (|d| < 2^31). */
static int32_t ceil_int(double d)
{
    int32_t i = (int32_t)d; /* toward zero */
    return (double)i < d ? i + 1 : i;
}

int ce_fixed_from(ce_fixed *f, const ce_set *s)
{
    int i, j, last;
    double v0, lo, hi, limit = 16384.0; /* |coefficient| < 2^14 deg/s keeps Q16 in int32 */
    if (f == NULL || s == NULL || !s->loaded) {
        return CE_ERR_ARG;
    }
    zero(f, sizeof *f);
    if (s->model != 0) {
        return CE_ERR_MODEL_KIND;
    }
    if (s->n_terms != 0) {
        return CE_ERR_TERM_KIND;
    }
    v0 = (double)s->v0_hi + (double)s->v0_lo;
    lo = (double)s->lo_hi + (double)s->lo_lo;
    hi = (double)s->hi_hi + (double)s->hi_lo;
    if (!(lo > -2147483000.0 && hi < 2147483000.0)) {
        return CE_ERR_LIMIT;
    }
    f->lo = ceil_int(lo);
    f->hi = ceil_int(hi) - ((double)ceil_int(hi) > hi ? 1 : 0); /* largest integer <= hi */
    for (i = 0; i + 1 < s->n_segments; i++) {
        f->knot[i] = ceil_int((double)s->knot_hi[i] + (double)s->knot_lo[i]);
    }
    f->v0_q16 = round_to_int(v0 * 65536.0);
    /* the float form's centred segments (see recentre): t = (dV - mid) / half, |t| <= 1 */
    for (i = 0; i < s->n_segments; i++) {
        double half = 1.0 / (double)s->seg_inv_half[i], mid = (double)s->seg_mid[i];
        double mult = 16384.0 / half; /* t_q30 = dv_q16 * 2^14 / half = (dv_q16 * mult) >> shift */
        double bound = 0.0, power = 1.0; /* |polynomial| for |t| <= 2: Horner stays below 2^30 */
        if (!(mid > -2147483000.0 / 65536.0 && mid < 2147483000.0 / 65536.0)) {
            return CE_ERR_LIMIT;
        }
        f->mid_q16[i] = round_to_int(mid * 65536.0);
        f->t_shift[i] = 0;
        while (mult < 536870912.0 && f->t_shift[i] < 60) {
            mult *= 2.0;
            f->t_shift[i]++;
        }
        if (!(mult < 1073741824.0) || f->t_shift[i] < 1) {
            return CE_ERR_LIMIT; /* a half-width below 2^-15 counts */
        }
        f->t_mult[i] = round_to_int(mult);
        for (j = 0; j < s->n_coeffs; j++) {
            bound += (s->coeffs[i][j] < 0.0f ? -(double)s->coeffs[i][j] : (double)s->coeffs[i][j]) * power;
            power *= 2.0;
        }
        if (!(bound < limit)) {
            return CE_ERR_LIMIT;
        }
        for (j = 0; j < s->n_coeffs; j++) {
            f->coeffs[i][j] = (int32_t)round_to_int((double)s->coeffs[i][j] * 65536.0);
        }
    }
    last = s->n_segments - 1;
    f->edge_lo_q30 = round_to_int(((double)s->dv_lo - (double)s->seg_mid[0]) * (double)s->seg_inv_half[0] * 1073741824.0);
    f->edge_hi_q30 =
        round_to_int(((double)s->dv_hi - (double)s->seg_mid[last]) * (double)s->seg_inv_half[last] * 1073741824.0);
    if (f->edge_lo_q30 < -2 * 1073741824LL || f->edge_hi_q30 > 2 * 1073741824LL) {
        return CE_ERR_LIMIT; /* |t| < 2 inside the span: powers of t stay in range */
    }
    f->n_segments = s->n_segments;
    f->n_coeffs = s->n_coeffs;
    f->loaded = 1;
    return CE_OK;
}

/* v / 2^bits rounded, for |v| < 2^62 - 2^(bits-1), with an unsigned shift (a signed one is
 * implementation-defined in C99) and no 64-bit division (a library call on a Cortex-M). */
static int64_t shift_round(int64_t v, int bits)
{
    uint64_t t = (uint64_t)(v + ((int64_t)1 << (bits - 1))) + ((uint64_t)1 << 62);
    return (int64_t)(t >> bits) - ((int64_t)1 << (62 - bits));
}

/* v clamped to +-(2^32 - 1): 65536 counts in Q16, a 16-bit sensor's whole range. */
static int64_t clamp32(int64_t v)
{
    const int64_t m = ((int64_t)1 << 32) - 1;
    return v > m ? m : v < -m ? -m : v;
}

int ce_fixed_eval(const ce_fixed *f, int32_t raw, int32_t *rate_q16)
{
    const int32_t *c;
    int64_t dv_q16, t, t_full, acc, slope, dt;
    int seg = 0, k, oos = 0;
    if (f == NULL || rate_q16 == NULL || !f->loaded) {
        return CE_ERR_ARG;
    }
    dv_q16 = clamp32((int64_t)raw * 65536 - f->v0_q16);
    if (raw < f->lo) {
        oos = 1;
        t = f->edge_lo_q30;
    } else if (raw > f->hi) {
        oos = 1;
        t = f->edge_hi_q30;
        seg = f->n_segments - 1;
    } else {
        while (seg + 1 < f->n_segments && raw >= f->knot[seg]) {
            seg++;
        }
    }
    /* |dv - mid| < 2^32, t_mult < 2^30: the product stays below 2^62 */
    t_full = shift_round(clamp32(dv_q16 - f->mid_q16[seg]) * f->t_mult[seg], f->t_shift[seg]);
    if (!oos) {
        t = t_full;
    }
    c = f->coeffs[seg];
    acc = c[f->n_coeffs - 1];
    for (k = f->n_coeffs - 2; k >= 0; k--) {
        acc = shift_round(acc * t, 30) + c[k];
    }
    if (oos && f->n_coeffs > 1) {
        /* |slope| <= sum k |c_k| <= sum |c_k| 2^k < 2^14 deg/s (Q16: 2^30) */
        slope = (int64_t)(f->n_coeffs - 1) * c[f->n_coeffs - 1];
        for (k = f->n_coeffs - 2; k >= 1; k--) {
            slope = shift_round(slope * t, 30) + (int64_t)k * c[k];
        }
        dt = shift_round(t_full - t, 10); /* beyond the span, in 2^-20 of t, at most 1024 half-widths */
        dt = dt > ((int64_t)1 << 30) ? (int64_t)1 << 30 : dt < -((int64_t)1 << 30) ? -((int64_t)1 << 30) : dt;
        acc += shift_round(slope * dt, 20); /* |product| < 2^60 */
    }
    if (acc > INT32_MAX) {
        acc = INT32_MAX;
    } else if (acc < INT32_MIN) {
        acc = INT32_MIN;
    }
    *rate_q16 = (int32_t)acc;
    return oos;
}

uint32_t ce_sizeof_set(void) { return (uint32_t)sizeof(ce_set); }

uint32_t ce_sizeof_fixed(void) { return (uint32_t)sizeof(ce_fixed); }

uint32_t ce_sizeof_coupling(void) { return (uint32_t)sizeof(ce_coupling); }

uint32_t ce_error_offset(const ce_set *set) { return set != NULL ? set->error_at : 0u; }

const char *ce_strerror(int code)
{
    switch (code) {
    case CE_OK:
        return "ok";
    case CE_ERR_ARG:
        return "bad argument or set not loaded";
    case CE_ERR_CRC:
        return "CRC mismatch";
    case CE_ERR_SYNTAX:
        return "not JSON (truncated, malformed or trailing bytes)";
    case CE_ERR_NOT_CANONICAL:
        return "not in canonical form";
    case CE_ERR_SCHEMA:
        return "schema not supported";
    case CE_ERR_FIELD:
        return "a field is missing, of the wrong type, not finite or of the wrong length";
    case CE_ERR_MODEL_KIND:
        return "model kind not supported";
    case CE_ERR_TERM_KIND:
        return "term kind not supported";
    case CE_ERR_LIMIT:
        return "beyond the device's limits (segments, coefficients, terms, nesting)";
    case CE_ERR_SENSOR:
        return "set is for another sensor";
    case CE_ERR_AXIS:
        return "set is for another axis";
    case CE_ERR_SPAN:
        return "span does not cover the rated range";
    case CE_ERR_INPUT:
        return "a term needs a channel the device does not have";
    case CE_ERR_COUPLING:
        return "coupling matrix singular or an off-diagonal term above 10 %";
    case CE_ERR_IMU_SET:
        return "coupling belongs to another IMU set (not these axes)";
    case CE_ERR_UNSIGNED:
        return "not signed";
    case CE_ERR_SIGNATURE_FORMAT:
        return "signature of the wrong length (truncated or garbage)";
    case CE_ERR_KEY:
        return "signed by another key than the device's trust key";
    case CE_ERR_SIGNATURE:
        return "signature does not match the content (changed, or for another sensor)";
    case CE_ERR_ROLLBACK:
        return "version older than the device has run (rollback)";
    default:
        return "unknown code";
    }
}
