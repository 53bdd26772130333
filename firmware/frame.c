/* See frame.h. Written for clarity over speed: a 34-byte frame costs well under 1 ms on the AVR. */
#include "frame.h"

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, MSB first, no final xor (check "123456789" = 0x29B1).
 * Bitwise rather than a 512-byte table: RAM is 2 KiB on the ATmega328P. */
uint16_t sp_crc16(const uint8_t *data, size_t n)
{
    uint16_t crc = 0xFFFFu;
    for (size_t i = 0; i < n; ++i) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (uint8_t b = 0; b < 8; ++b)
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    }
    return crc;
}

/* Consistent Overhead Byte Stuffing (Cheshire & Baker): no 0x00 in the output. */
size_t sp_cobs_encode(const uint8_t *src, size_t n, uint8_t *dst)
{
    size_t code_at = 0, out = 1;
    uint8_t code = 1;
    for (size_t i = 0; i < n; ++i) {
        if (src[i] == 0) {
            dst[code_at] = code;
            code_at = out++;
            code = 1;
        } else {
            dst[out++] = src[i];
            if (++code == 0xFF) {
                dst[code_at] = code;
                code_at = out++;
                code = 1;
            }
        }
    }
    dst[code_at] = code;
    return out;
}

size_t sp_cobs_decode(const uint8_t *src, size_t n, uint8_t *dst, size_t cap)
{
    size_t i = 0, out = 0;
    while (i < n) {
        uint8_t code = src[i++];
        if (code == 0)
            return (size_t)-1;
        for (uint8_t k = 1; k < code; ++k) {
            if (i >= n || src[i] == 0 || out >= cap)
                return (size_t)-1;
            dst[out++] = src[i++];
        }
        if (code != 0xFF && i < n) {
            if (out >= cap)
                return (size_t)-1;
            dst[out++] = 0;
        }
    }
    return out;
}

size_t sp_frame(const uint8_t *payload, size_t n, uint8_t *out)
{
    uint8_t tmp[SP_MAX_PAYLOAD + 2];
    if (n > SP_MAX_PAYLOAD)
        return 0;
    for (size_t i = 0; i < n; ++i)
        tmp[i] = payload[i];
    uint16_t crc = sp_crc16(payload, n);
    tmp[n] = (uint8_t)(crc & 0xFF);
    tmp[n + 1] = (uint8_t)(crc >> 8);
    size_t lead = (n > 0 && payload[0] == 1u) ? 0u : 1u; /* version 1 frames have no leading 0x00 */
    if (lead)
        out[0] = 0x00;
    size_t len = lead + sp_cobs_encode(tmp, n + 2, out + lead);
    out[len++] = 0x00;
    return len;
}

int sp_unframe(const uint8_t *body, size_t n, uint8_t *payload, size_t cap)
{
    uint8_t tmp[SP_MAX_PAYLOAD + 2];
    size_t len = sp_cobs_decode(body, n, tmp, sizeof tmp);
    if (len == (size_t)-1)
        return SP_ERR_COBS;
    if (len < 4 || len - 2 > cap)
        return SP_ERR_LENGTH;
    len -= 2;
    uint16_t crc = (uint16_t)(tmp[len] | ((uint16_t)tmp[len + 1] << 8));
    if (crc != sp_crc16(tmp, len))
        return SP_ERR_CRC;
    for (size_t i = 0; i < len; ++i)
        payload[i] = tmp[i];
    return (int)len;
}

static uint8_t *put16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    return p + 2;
}

static uint8_t *put32(uint8_t *p, uint32_t v)
{
    for (uint8_t i = 0; i < 4; ++i)
        p[i] = (uint8_t)(v >> (8 * i));
    return p + 4;
}

uint16_t sp_get_u16(const uint8_t *p) { return (uint16_t)(p[0] | ((uint16_t)p[1] << 8)); }

uint32_t sp_get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

size_t sp_pack_data(uint8_t *p, uint16_t seq, uint32_t t_us, uint16_t osr, const uint32_t raw[SP_N_CHANNELS])
{
    uint8_t *q = p;
    *q++ = SP_PROTOCOL_VERSION;
    *q++ = SP_MSG_DATA;
    q = put16(q, seq);
    q = put32(q, t_us);
    q = put16(q, osr);
    for (uint8_t i = 0; i < SP_N_CHANNELS; ++i)
        q = put32(q, raw[i]);
    return (size_t)(q - p);
}

size_t sp_pack_info(uint8_t *p, uint16_t seq, uint32_t t_us, const uint8_t fw[3], uint16_t osr)
{
    uint8_t *q = p;
    *q++ = SP_PROTOCOL_VERSION;
    *q++ = SP_MSG_INFO;
    q = put16(q, seq);
    q = put32(q, t_us);
    *q++ = fw[0];
    *q++ = fw[1];
    *q++ = fw[2];
    *q++ = SP_N_CHANNELS;
    q = put16(q, osr);
    return (size_t)(q - p);
}
