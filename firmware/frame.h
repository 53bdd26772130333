/* Frame encoder/decoder of the softphantom sensing protocol (docs/protocol.md).
 *
 * version 2: frame = 0x00 || COBS(payload || CRC-16/CCITT-FALSE(payload) little-endian) || 0x00
 * (version 1 had no leading 0x00; the leading delimiter ends any damaged frame before this one,
 * so the receiver never loses a good frame to a bad one). Byte 0 of the payload is the version.
 * Plain C99, no allocation: compiles for the ATmega328P (avr-gcc) and on the host (gcc), where a
 * test checks it byte for byte against the Python implementation (softphantom.sensing.protocol).
 */
#ifndef SP_FRAME_H
#define SP_FRAME_H

#include <stddef.h>
#include <stdint.h>

#define SP_PROTOCOL_VERSION 2u
#define SP_PROTOCOL_VERSION_MIN 1u /* commands of version 1 are still read */
#define SP_MSG_DATA 0x01u
#define SP_MSG_INFO 0x02u
#define SP_CMD_SET_OSR 0x10u
#define SP_CMD_GET_INFO 0x11u

/* The channel count, fixed at build time (make N_CHANNELS=n): the arms, then the urethra. The
 * BIP's board reads 5; an Arduino UNO has 6 analog inputs (A0-A5), a Mega 2560 16. */
#ifndef SP_N_CHANNELS
#define SP_N_CHANNELS 5u
#endif
#if SP_N_CHANNELS < 2 || SP_N_CHANNELS > 16
#error "SP_N_CHANNELS: a board reads 2..16 channels"
#endif
#define SP_DATA_PAYLOAD (10u + 4u * SP_N_CHANNELS) /* ver, type, seq u16, t_us u32, osr u16, n x u32 */
#define SP_INFO_PAYLOAD 14u   /* ver, type, seq u16, t_us u32, fw x3, n_ch, osr u16 */
#define SP_MAX_PAYLOAD (SP_DATA_PAYLOAD + 2u)
/* COBS adds 1 byte per started 254-byte block; + CRC 2 + two delimiters */
#define SP_MAX_FRAME (SP_MAX_PAYLOAD + 2u + 1u + 2u)

/* Errors of sp_unframe (negative return values). */
#define SP_ERR_COBS (-1)
#define SP_ERR_LENGTH (-2)
#define SP_ERR_CRC (-3)

uint16_t sp_crc16(const uint8_t *data, size_t n);
size_t sp_cobs_encode(const uint8_t *src, size_t n, uint8_t *dst);
/* Returns the decoded length, or (size_t)-1 on a malformed input or if it exceeds cap. */
size_t sp_cobs_decode(const uint8_t *src, size_t n, uint8_t *dst, size_t cap);

/* Frame a payload into out (room for SP_MAX_FRAME bytes): 0x00, COBS body, 0x00 (payload[0] == 1:
 * version 1, no leading 0x00); returns the length incl. the delimiters. */
size_t sp_frame(const uint8_t *payload, size_t n, uint8_t *out);
/* Decode a frame body (without its 0x00) into payload; returns the payload length or SP_ERR_*. */
int sp_unframe(const uint8_t *body, size_t n, uint8_t *payload, size_t cap);

size_t sp_pack_data(uint8_t *p, uint16_t seq, uint32_t t_us, uint16_t osr, const uint32_t raw[SP_N_CHANNELS]);
size_t sp_pack_info(uint8_t *p, uint16_t seq, uint32_t t_us, const uint8_t fw[3], uint16_t osr);

uint16_t sp_get_u16(const uint8_t *p);
uint32_t sp_get_u32(const uint8_t *p);

#endif
