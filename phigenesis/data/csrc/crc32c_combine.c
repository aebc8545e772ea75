/* CRC-32C of a concatenation from the CRC-32Cs of its parts (phigenesis/data/native.py).
 *
 * The shard writer checksums each column of a row as it writes it; with this, the CRC-32C of
 * the whole file follows from those values and the lengths, instead of a second pass over every
 * byte (a tenth of a Waymo frame's write). CRC-32C is linear over GF(2): for byte strings A and B,
 * crc(A B) = crc(A) * x^(8 |B|) + crc(B) mod P, the pre- and post-inversions cancelling. Values
 * are polynomials in the reflected bit order CRC-32C uses: bit 31 holds x^0, bit 0 x^31.
 */
#include <stdint.h>

#define CRC32C_POLY_REFLECTED 0x82f63b78u
#define X_POWER(k) (0x80000000u >> (k)) /* x^k for k < 32, reflected */

/* a * b mod P. */
static uint32_t multiply_mod_p(uint32_t a, uint32_t b) {
    uint32_t product = 0;
    for (int k = 0; k < 32; ++k) {
        if (a & X_POWER(k)) product ^= b; /* add b * x^k (b holds b0 * x^k here) */
        b = (b & 1u) ? (b >> 1) ^ CRC32C_POLY_REFLECTED : b >> 1; /* b *= x */
    }
    return product;
}

/* The CRC-32C of A then B, given crc_a = CRC-32C(A), crc_b = CRC-32C(B) and B's length. */
uint32_t phigenesis_crc32c_combine(uint32_t crc_a, uint32_t crc_b, uint64_t length_b) {
    uint32_t shift = X_POWER(0), power = X_POWER(8); /* x^(8 * length_b), by squaring x^8 */
    for (; length_b; length_b >>= 1) {
        if (length_b & 1u) shift = multiply_mod_p(shift, power);
        power = multiply_mod_p(power, power);
    }
    return multiply_mod_p(shift, crc_a) ^ crc_b;
}
