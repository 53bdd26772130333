/* Host-side driver of frame.c for the golden-frame tests (tests/test_firmware.py).
 *   frame_tool data SEQ T_US OSR R0 .. R(n-1)     -> hex of the DATA frame (with 0x00; n = SP_N_CHANNELS)
 *   frame_tool info SEQ T_US MAJ MIN PATCH OSR     -> hex of the INFO frame
 *   frame_tool decode HEX                          -> fields of one frame body (without 0x00)
 *   frame_tool crc STRING                          -> CRC-16 of the ASCII string
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "../frame.h"

static void print_hex(const uint8_t *b, size_t n)
{
    for (size_t i = 0; i < n; ++i)
        printf("%02x", b[i]);
    printf("\n");
}

int main(int argc, char **argv)
{
    uint8_t payload[SP_MAX_PAYLOAD], out[SP_MAX_FRAME];
    if (argc >= 5 + (int)SP_N_CHANNELS && strcmp(argv[1], "data") == 0) {
        uint32_t raw[SP_N_CHANNELS];
        for (int i = 0; i < (int)SP_N_CHANNELS; ++i)
            raw[i] = (uint32_t)strtoul(argv[5 + i], NULL, 0);
        size_t n = sp_pack_data(payload, (uint16_t)strtoul(argv[2], NULL, 0),
                                (uint32_t)strtoul(argv[3], NULL, 0), (uint16_t)strtoul(argv[4], NULL, 0), raw);
        print_hex(out, sp_frame(payload, n, out));
        return 0;
    }
    if (argc >= 8 && strcmp(argv[1], "info") == 0) {
        uint8_t fw[3] = {(uint8_t)atoi(argv[4]), (uint8_t)atoi(argv[5]), (uint8_t)atoi(argv[6])};
        size_t n = sp_pack_info(payload, (uint16_t)strtoul(argv[2], NULL, 0),
                                (uint32_t)strtoul(argv[3], NULL, 0), fw, (uint16_t)strtoul(argv[7], NULL, 0));
        print_hex(out, sp_frame(payload, n, out));
        return 0;
    }
    if (argc >= 3 && strcmp(argv[1], "crc") == 0) {
        printf("%04x\n", sp_crc16((const uint8_t *)argv[2], strlen(argv[2])));
        return 0;
    }
    if (argc >= 3 && strcmp(argv[1], "decode") == 0) {
        uint8_t body[256];
        size_t n = strlen(argv[2]) / 2;
        if (n > sizeof body)
            n = sizeof body;
        for (size_t i = 0; i < n; ++i) {
            unsigned v;
            sscanf(argv[2] + 2 * i, "%2x", &v);
            body[i] = (uint8_t)v;
        }
        int len = sp_unframe(body, n, payload, sizeof payload);
        if (len < 0) {
            printf("error %s\n", len == SP_ERR_COBS ? "cobs" : len == SP_ERR_CRC ? "crc" : "length");
            return 0;
        }
        printf("version %u type %u len %d", payload[0], len > 1 ? payload[1] : 0, len);
        if (len == SP_DATA_PAYLOAD && payload[1] == SP_MSG_DATA) {
            printf(" seq %u t_us %lu osr %u raw", sp_get_u16(payload + 2), (unsigned long)sp_get_u32(payload + 4),
                   sp_get_u16(payload + 8));
            for (int i = 0; i < (int)SP_N_CHANNELS; ++i)
                printf(" %lu", (unsigned long)sp_get_u32(payload + 10 + 4 * i));
        } else if (len == 4 && payload[1] == SP_CMD_SET_OSR) {
            printf(" osr %u", sp_get_u16(payload + 2));
        }
        printf("\n");
        return 0;
    }
    fprintf(stderr, "usage: frame_tool data|info|decode|crc ...\n");
    return 2;
}
