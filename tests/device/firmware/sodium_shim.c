/*
 * The tests' device crypto: canical_eval's signature check given libsodium's Ed25519 verification,
 * as an MCU gives its vendor's. libsodium is the distribution's runtime library (libsodium23, no
 * headers), so its two functions are declared here as libsodium's sodium.h declares them.
 */
#include <stddef.h>
#include <stdint.h>

#include "canical_eval.h"

int sodium_init(void);
int crypto_sign_verify_detached(const unsigned char *sig, const unsigned char *m, unsigned long long mlen,
                                const unsigned char *pk);

/* Room for the largest signed message: an IMU set of four full banks (16384 bytes each). */
static uint8_t scratch[CE_SIGNED_HEADER_MAX + 4u * 16384u + 64u];

static int verify(void *context, const uint8_t *signature, const uint8_t *message, uint32_t length,
                  const uint8_t *public_key)
{
    (void)context;
    return crypto_sign_verify_detached(signature, message, length, public_key);
}

/* sodium_init's result: 0 initialised, 1 already, -1 failed. */
int shim_init(void)
{
    return sodium_init();
}

static ce_trust trust_of(const uint8_t *public_key, const uint8_t *key_id, uint64_t counter)
{
    ce_trust trust;
    trust.public_key = public_key;
    trust.key_id = key_id;
    trust.counter = counter;
    trust.verify = verify;
    trust.context = NULL;
    trust.scratch = scratch;
    trust.scratch_size = (uint32_t)sizeof scratch;
    return trust;
}

int shim_check(const uint8_t *public_key, const uint8_t *key_id, uint64_t counter, const uint8_t *signature,
               uint32_t signature_length, const uint8_t *content, uint32_t length, uint32_t serial,
               uint64_t *version)
{
    ce_trust trust = trust_of(public_key, key_id, counter);
    return ce_signature_check(&trust, signature, signature_length, content, length, serial, version);
}

int shim_check3(const uint8_t *public_key, const uint8_t *key_id, uint64_t counter, const uint8_t *signature,
                uint32_t signature_length, const uint8_t *content, uint32_t length,
                const uint8_t *const axis_content[3], const uint32_t axis_length[3], uint32_t serial,
                uint64_t *version)
{
    ce_trust trust = trust_of(public_key, key_id, counter);
    return ce_signature_check3(&trust, signature, signature_length, content, length, axis_content, axis_length,
                               serial, version);
}
