/*
 * Test driver for canical_eval, built by the tests with -fsanitize=address,undefined.
 *
 *   fuzz_driver cases FILE SERIAL AXIS RANGE INPUTS...
 *       FILE holds records (u32 little-endian length, u32 declared CRC, bytes); each is loaded
 *       from a heap block of exactly its length (so a read past the end is an ASan report)
 *       and, when accepted, evaluated on a few samples (float, and fixed point where it applies). Writes one line per record: the code.
 *   fuzz_driver mutate FILE N SEED SERIAL AXIS RANGE INPUTS...
 *       N random mutations of the records in FILE (byte flips, insertions, deletions,
 *       truncations, digit and bracket swaps; CRC recomputed for 7 in 8 so the parser is
 *       reached). Writes "code crc hex" for each accepted payload and, with environment
 *       CE_SAMPLE_EVERY=k, for every k-th refused one past the CRC check; then
 *       "cases N accepted A".
 *   fuzz_driver coupling FILE N SEED IMU_SET_ID SERIAL AXIS RANGE INPUTS...
 *       FILE holds the x, y, z axis banks and an IMU set's coupling bank (four records). The
 *       first case is the coupling bank as given, then N - 1 random mutations of it (as mutate
 *       does); each is loaded by ce_coupling_load with the three axis banks and IMU_SET_ID (each
 *       from an exactly sized heap block) and, when accepted, runs a few three-axis samples.
 *       Output as mutate's.
 *
 * Exit status 0 unless an argument or file is bad; a sanitizer report aborts the process.
 */
#include "canical_eval.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static uint64_t rng_state = 88172645463325252ull;

static uint32_t next_u32(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return (uint32_t)(rng_state >> 11);
}

typedef struct {
    uint8_t *data;
    uint32_t len;
    uint32_t crc;
} record;

static record *read_records(const char *path, uint32_t *count)
{
    FILE *f = fopen(path, "rb");
    record *out = NULL;
    uint32_t n = 0, cap = 0;
    uint8_t head[8];
    if (f == NULL) {
        return NULL;
    }
    while (fread(head, 1, 8, f) == 8) {
        uint32_t len = head[0] | (uint32_t)head[1] << 8 | (uint32_t)head[2] << 16 | (uint32_t)head[3] << 24;
        uint32_t crc = head[4] | (uint32_t)head[5] << 8 | (uint32_t)head[6] << 16 | (uint32_t)head[7] << 24;
        if (n == cap) {
            cap = cap ? 2 * cap : 1024;
            out = realloc(out, cap * sizeof *out);
            if (out == NULL) {
                exit(3);
            }
        }
        out[n].data = malloc(len ? len : 1);
        if (out[n].data == NULL || fread(out[n].data, 1, len, f) != len) {
            exit(3);
        }
        out[n].len = len;
        out[n].crc = crc;
        n++;
    }
    fclose(f);
    *count = n;
    return out;
}

/* Load from an exactly sized heap copy; run a few samples through an accepted set. */
static int try_load(const uint8_t *data, uint32_t len, uint32_t crc, const ce_device *device)
{
    static ce_set set;
    uint8_t *copy = malloc(len ? len : 1);
    float inputs[CE_MAX_INPUTS] = {25.0f, 12.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    int code, i;
    if (copy == NULL) {
        exit(3);
    }
    memcpy(copy, data, len);
    code = ce_load(&set, copy, len, crc, device);
    free(copy);
    if (code == CE_OK) {
        static ce_fixed fixed;
        if (ce_fixed_from(&fixed, &set) == CE_OK) {
            for (i = 0; i < 64; i++) {
                int32_t q;
                if (ce_fixed_eval(&fixed, (int32_t)(next_u32() % 65536u) - 32768, &q) < 0) {
                    exit(4);
                }
            }
        }
        for (i = 0; i < 64; i++) {
            ce_sample s;
            float rate;
            s.raw = (float)((int32_t)(next_u32() % 80000u) - 40000);
            /* 100 ms apart across the counter's wrap: lag and derivative terms with tau of a few
             * seconds reach their lag phase; channels that move flip direction terms */
            s.time_ms = 0xFFFFF000u + (uint32_t)i * 100u;
            inputs[0] = 25.0f + (float)(next_u32() % 7u) * 0.3f;
            inputs[1] = 12.0f + (float)(next_u32() % 5u) * 0.02f;
            s.inputs = inputs;
            if (ce_eval(&set, &s, &rate) < 0) {
                exit(4);
            }
        }
    }
    return code;
}

/* A coupling bank loaded with the three axis banks (exactly sized heap copies, all of them); an
 * accepted one runs a few three-axis samples through ce_eval3. */
static int try_coupling(const uint8_t *data, uint32_t len, uint32_t crc, uint32_t imu_set_id, const record *axes,
                        const ce_device *device)
{
    static ce_coupling coupling;
    static ce_set sets[3];
    ce_set *ptrs[3];
    uint8_t *copies[3];
    uint32_t lengths[3];
    const uint8_t *contents[3];
    uint8_t *copy = malloc(len ? len : 1);
    float inputs[CE_MAX_INPUTS] = {25.0f, 12.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    int code, i, k;
    if (copy == NULL) {
        exit(3);
    }
    memcpy(copy, data, len);
    for (k = 0; k < 3; k++) {
        copies[k] = malloc(axes[k].len ? axes[k].len : 1);
        if (copies[k] == NULL) {
            exit(3);
        }
        memcpy(copies[k], axes[k].data, axes[k].len);
        contents[k] = copies[k];
        lengths[k] = axes[k].len;
    }
    code = ce_coupling_load(&coupling, copy, len, crc, imu_set_id, contents, lengths, device);
    if (code == CE_OK) {
        for (k = 0; k < 3; k++) {
            ce_device d = *device;
            d.axis = (char)('x' + k);
            if (ce_load(&sets[k], copies[k], lengths[k], axes[k].crc, &d) != CE_OK) {
                exit(5); /* the axis banks given must be valid */
            }
            ptrs[k] = &sets[k];
        }
        for (i = 0; i < 64; i++) {
            ce_sample3 s;
            float rate[3];
            uint8_t oos[3];
            for (k = 0; k < 3; k++) {
                s.raw[k] = (float)((int32_t)(next_u32() % 80000u) - 40000);
            }
            s.time_ms = (uint32_t)i * 100u;
            s.inputs = inputs;
            if (ce_eval3(ptrs, &coupling, &s, rate, oos) < 0) {
                exit(4);
            }
        }
    }
    for (k = 0; k < 3; k++) {
        free(copies[k]);
    }
    free(copy);
    return code;
}

static void mutate(uint8_t *buf, uint32_t *len, uint32_t cap)
{
    uint32_t op = next_u32() % 8u, pos = *len ? next_u32() % *len : 0, k;
    static const char tokens[] = "0123456789-+.eE[]{},:\"\\ntfu";
    switch (op) {
    case 0: /* flip a bit */
        if (*len) {
            buf[pos] ^= (uint8_t)(1u << (next_u32() % 8u));
        }
        break;
    case 1: /* a JSON-ish byte */
        if (*len) {
            buf[pos] = (uint8_t)tokens[next_u32() % (sizeof tokens - 1)];
        }
        break;
    case 2: /* insert */
        if (*len < cap) {
            memmove(buf + pos + 1, buf + pos, *len - pos);
            buf[pos] = (uint8_t)tokens[next_u32() % (sizeof tokens - 1)];
            (*len)++;
        }
        break;
    case 3: /* delete */
        if (*len) {
            memmove(buf + pos, buf + pos + 1, *len - pos - 1);
            (*len)--;
        }
        break;
    case 4: /* truncate */
        *len = pos;
        break;
    case 5: /* another digit */
        for (k = 0; k < *len; k++) {
            uint32_t i = (pos + k) % *len;
            if (buf[i] >= '0' && buf[i] <= '9') {
                buf[i] = (uint8_t)('0' + next_u32() % 10u);
                break;
            }
        }
        break;
    case 6: /* duplicate a chunk (longer lists, deeper nesting) */
    {
        uint8_t chunk[64];
        uint32_t n = 1 + next_u32() % 64u, at = next_u32() % (*len + 1);
        if (pos + n <= *len && *len + n <= cap) {
            memcpy(chunk, buf + pos, n);
            memmove(buf + at + n, buf + at, *len - at);
            memcpy(buf + at, chunk, n);
            *len += n;
        }
        break;
    }
    default: /* random byte */
        if (*len) {
            buf[pos] = (uint8_t)next_u32();
        }
        break;
    }
}

int main(int argc, char **argv)
{
    const char *names[CE_MAX_INPUTS];
    ce_device device;
    record *recs;
    uint32_t n_recs = 0, i;
    int first_dev, mode_mutate, mode_coupling;
    if (argc < 2) {
        return 2;
    }
    mode_mutate = strcmp(argv[1], "mutate") == 0;
    mode_coupling = strcmp(argv[1], "coupling") == 0;
    first_dev = mode_coupling ? 6 : mode_mutate ? 5 : 3;
    if (argc < first_dev + 3 || argc - (first_dev + 3) > CE_MAX_INPUTS) {
        fprintf(stderr, "usage: see the comment at the top of fuzz_driver.c\n");
        return 2;
    }
    device.serial = (uint32_t)strtoul(argv[first_dev], NULL, 10);
    device.axis = argv[first_dev + 1][0];
    device.rated_range_dps = (float)strtod(argv[first_dev + 2], NULL);
    device.n_inputs = (uint8_t)(argc - (first_dev + 3));
    for (i = 0; i < device.n_inputs; i++) {
        names[i] = argv[first_dev + 3 + (int)i];
    }
    device.inputs = names;
    recs = read_records(argv[2], &n_recs);
    if (recs == NULL || n_recs == 0) {
        return 2;
    }
    if (mode_coupling) {
        uint32_t n = (uint32_t)strtoul(argv[3], NULL, 10), accepted = 0, j, cap = 32768;
        uint32_t imu_set_id = (uint32_t)strtoul(argv[5], NULL, 10);
        uint32_t sample_every = getenv("CE_SAMPLE_EVERY") ? (uint32_t)strtoul(getenv("CE_SAMPLE_EVERY"), NULL, 10) : 0u;
        uint8_t *buf = malloc(cap);
        rng_state ^= strtoull(argv[4], NULL, 10) * 0x9E3779B97F4A7C15ull;
        if (buf == NULL || n_recs != 4 || recs[3].len > cap) {
            return 2;
        }
        for (i = 0; i < n; i++) {
            uint32_t len = recs[3].len, crc = recs[3].crc, rounds = i == 0 ? 0 : 1 + next_u32() % 4u;
            int code;
            memcpy(buf, recs[3].data, len);
            for (j = 0; j < rounds; j++) {
                mutate(buf, &len, cap);
            }
            if (rounds) {
                crc = next_u32() % 8u ? ce_crc32(buf, len) : next_u32();
            }
            code = try_coupling(buf, len, crc, imu_set_id, recs, &device);
            if (code == CE_OK || (sample_every != 0u && i % sample_every == 0u && code != CE_ERR_CRC)) {
                accepted += code == CE_OK;
                printf("%d %08x ", code, crc);
                for (j = 0; j < len; j++) {
                    printf("%02x", buf[j]);
                }
                printf("\n");
            }
        }
        printf("cases %u accepted %u\n", n, accepted);
        free(buf);
    } else if (!mode_mutate) {
        for (i = 0; i < n_recs; i++) {
            printf("%d\n", try_load(recs[i].data, recs[i].len, recs[i].crc, &device));
        }
    } else {
        uint32_t n = (uint32_t)strtoul(argv[3], NULL, 10), accepted = 0, j, cap = 32768;
        uint32_t sample_every = getenv("CE_SAMPLE_EVERY") ? (uint32_t)strtoul(getenv("CE_SAMPLE_EVERY"), NULL, 10) : 0u;
        uint8_t *buf = malloc(cap);
        rng_state ^= strtoull(argv[4], NULL, 10) * 0x9E3779B97F4A7C15ull;
        if (buf == NULL) {
            return 3;
        }
        for (i = 0; i < n; i++) {
            const record *seed = &recs[next_u32() % n_recs];
            uint32_t len = seed->len, crc, rounds = 1 + next_u32() % 4u;
            memcpy(buf, seed->data, len);
            for (j = 0; j < rounds; j++) {
                mutate(buf, &len, cap);
            }
            int code;
            crc = next_u32() % 8u ? ce_crc32(buf, len) : next_u32();
            code = try_load(buf, len, crc, &device);
            if (code == CE_OK || (sample_every != 0u && i % sample_every == 0u && code != CE_ERR_CRC)) {
                accepted += code == CE_OK;
                printf("%d %08x ", code, crc);
                for (j = 0; j < len; j++) {
                    printf("%02x", buf[j]);
                }
                printf("\n");
            }
        }
        printf("cases %u accepted %u\n", n, accepted);
        free(buf);
    }
    for (i = 0; i < n_recs; i++) {
        free(recs[i].data);
    }
    free(recs);
    return 0;
}
