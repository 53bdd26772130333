/* softphantom sensing board: Arduino UNO (ATmega328P) or Mega 2560 (ATmega2560), both 16 MHz; plain
 * C with avr-libc (make BOARD=uno|mega, docs/protocol.md).
 *
 * Reads ADC0..ADC(n-2) (the arm transducers, MPXV7002; the BIP's four: front_zpos, front_zneg,
 * back_xpos, back_xneg) and ADC(n-1) (urethra, MPX4250D) against AVcc (= the transducers' supply
 * VS, so the reading is ratiometric), sums N readings per channel round-robin (N = OSR, default
 * 100, 1..500), and sends one DATA frame per window (docs/protocol.md) at 115200 baud. The
 * channel count n = SP_N_CHANNELS is fixed at build time (make N_CHANNELS=n; 5 for the BIP); the
 * UNO has 6 analog inputs (A0-A5), the Mega 16 (A0-A15 = ADC0..ADC15), so n <= 6 or n <= 16.
 * The ADC runs free (auto-trigger): one conversion every 13 ADC clocks = 104 us exactly, back to
 * back, summed by its interrupt; so the frame time is exactly n * N * 104 us (n = 5, N = 100:
 * 19.2 Hz, N = 25: 76.9 Hz) and nothing the main loop does (packing, CRC, commands, a full TX
 * buffer) delays or drops a sample.
 * Timestamp: Timer1 at clk/8 (0.5 us ticks) extended by its overflow interrupt, in us (u32,
 * wraps after 71.6 min); a frame carries the centre of its sampling window.
 * Commands (host -> board): SET_OSR, GET_INFO, of protocol version 1 or 2; the board answers both
 * with an INFO frame. Frames go out in version 2: 0x00 || COBS(payload || CRC) || 0x00.
 * TX is interrupt-driven from a ring buffer, so sampling continues while a frame goes out.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <util/atomic.h>
#include <stdint.h>

#include "frame.h"

#if defined(__AVR_ATmega328P__)
#if SP_N_CHANNELS > 6
#error "the Arduino UNO has 6 analog inputs (A0-A5): build with N_CHANNELS <= 6 (or BOARD=mega, 16)"
#endif
#define UART_RX_vect USART_RX_vect
#define UART_UDRE_vect USART_UDRE_vect
#elif defined(__AVR_ATmega2560__)
#if SP_N_CHANNELS > 16
#error "the Arduino Mega 2560 has 16 analog inputs (A0-A15): build with N_CHANNELS <= 16"
#endif
/* the Mega's USB serial is USART0: the UNO's registers (UDR0, UCSR0B, ...), other vector names */
#define UART_RX_vect USART0_RX_vect
#define UART_UDRE_vect USART0_UDRE_vect
#else
#error "a board is the Arduino UNO (-mmcu=atmega328p) or Mega 2560 (-mmcu=atmega2560)"
#endif

#define FW_MAJOR 2 /* 2.x speaks protocol version 2 (a 0x00 before each frame) */
#define FW_MINOR 0
#define FW_PATCH 0
#define BAUD_UBRR 16 /* 16 MHz / (8 * (16 + 1)) = 117647 baud with U2X (+2.1 %), the Arduino setting */
#define OSR_DEFAULT 100u
/* 6 * 500 * 104 us = 0.31 s per frame at most, inside the host's 0.5 s silence limit; above 9 channels
 * (the Mega) it needs N < 4800 / n (docs/protocol.md) */
#define OSR_MAX 500u

/* ---- time ---- */
static volatile uint32_t t1_overflows;

ISR(TIMER1_OVF_vect) { ++t1_overflows; }

static uint32_t micros32(void)
{
    uint8_t sreg = SREG;
    cli();
    uint32_t ovf = t1_overflows;
    uint16_t tcnt = TCNT1;
    if ((TIFR1 & _BV(TOV1)) && tcnt < 0x8000u) /* overflow pending but not yet serviced */
        ++ovf;
    SREG = sreg;
    /* one overflow = 65536 ticks of 0.5 us = 32768 us; u32 arithmetic wraps at 2^32 us */
    return (ovf << 15) + (uint32_t)(tcnt >> 1);
}

/* ---- UART: TX ring buffer (interrupt-driven), RX ring buffer ---- */
#define TXBUF 128u /* power of two; holds three DATA frames of 5 channels (35 bytes each), 1.6 of 16 (79) */
#define RXBUF 64u
static volatile uint8_t tx_buf[TXBUF];
static volatile uint8_t tx_head, tx_tail;
static volatile uint8_t rx_buf[RXBUF];
static volatile uint8_t rx_head, rx_tail;

ISR(UART_UDRE_vect)
{
    if (tx_head == tx_tail) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = tx_buf[tx_tail];
    tx_tail = (uint8_t)((tx_tail + 1u) & (TXBUF - 1u));
}

ISR(UART_RX_vect)
{
    uint8_t c = UDR0;
    uint8_t next = (uint8_t)((rx_head + 1u) & (RXBUF - 1u));
    if (next != rx_tail) { /* drop on overflow; the host's command is then simply lost */
        rx_buf[rx_head] = c;
        rx_head = next;
    }
}

static void uart_init(void)
{
    UBRR0H = 0;
    UBRR0L = BAUD_UBRR;
    UCSR0A = _BV(U2X0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
    UCSR0B = _BV(TXEN0) | _BV(RXEN0) | _BV(RXCIE0);
}

static void uart_write(const uint8_t *b, uint8_t n)
{
    for (uint8_t i = 0; i < n; ++i) {
        uint8_t next = (uint8_t)((tx_head + 1u) & (TXBUF - 1u));
        while (next == tx_tail) /* full: wait (only when the UART is the bottleneck, N <= 5) */
            ;
        tx_buf[tx_head] = b[i];
        tx_head = next;
        UCSR0B |= _BV(UDRIE0);
    }
}

static int uart_getc(void)
{
    if (rx_head == rx_tail)
        return -1;
    uint8_t c = rx_buf[rx_tail];
    rx_tail = (uint8_t)((rx_tail + 1u) & (RXBUF - 1u));
    return c;
}

/* ---- ADC: free-running, summed in its interrupt ---- */
static volatile uint16_t osr = OSR_DEFAULT; /* N of the next window */
static volatile uint32_t acc[SP_N_CHANNELS]; /* sums of the window in progress */
static uint16_t acc_k;                        /* readings per channel taken in it */
static uint16_t acc_n;                        /* its N */
static uint8_t ch_conv, ch_mux;               /* channel converting now / latched by the next */
static uint8_t discard = 1;                   /* the first conversion (25 ADC clocks) is not used */
static uint32_t t_window_start;
static volatile uint16_t win_seq;             /* seq of the window in progress */

/* the last completed window, for the main loop; overwritten if it has not taken it yet (only
 * when the UART cannot carry every frame, N <= 5: the host sees the skipped seq) */
static volatile uint8_t done_ready;
static uint32_t done_sum[SP_N_CHANNELS];
static uint32_t done_t_us;
static uint16_t done_n, done_seq;

static void adc_init(void)
{
    ADMUX = _BV(REFS0); /* AVcc reference: ratiometric with VS; channel 0 first */
    ADCSRB = 0;         /* auto-trigger source: free running */
#if SP_N_CHANNELS > 8
    DIDR0 = 0xFFu; /* digital input buffers off on the channels read: ADC0..7 here, ADC8.. in DIDR2 */
    DIDR2 = (uint8_t)((1u << (SP_N_CHANNELS - 8u)) - 1u);
#else
    DIDR0 = (uint8_t)((1u << SP_N_CHANNELS) - 1u); /* digital input buffers off on the channels read */
#endif
    /* prescaler 128 (125 kHz), interrupt on, auto-trigger, start */
    ADCSRA = _BV(ADEN) | _BV(ADSC) | _BV(ADATE) | _BV(ADIE) | _BV(ADPS2) | _BV(ADPS1) | _BV(ADPS0);
}

ISR(ADC_vect)
{
    uint16_t v = ADC;      /* read before ADMUX changes */
    uint8_t ch = ch_conv;  /* the channel of this result */
    /* free running: the next conversion has already started with the channel in ADMUX; the
     * channel written now is taken by the one after it */
    ch_conv = ch_mux;
    ch_mux = (uint8_t)(ch_mux + 1u == SP_N_CHANNELS ? 0u : ch_mux + 1u);
#if SP_N_CHANNELS > 8
    /* ADC8..15 are MUX5:0 = 100xxx: MUX5 is bit 3 of ADCSRB (its ADTS stay 0, free running);
     * like MUX4:0 it is taken when the next conversion starts, so the pair changes together */
    ADCSRB = (uint8_t)(ch_mux >= 8u ? _BV(MUX5) : 0u);
    ADMUX = (uint8_t)(_BV(REFS0) | (ch_mux & 7u));
#else
    ADMUX = (uint8_t)(_BV(REFS0) | ch_mux);
#endif
    if (discard) {
        discard = 0; /* results follow as 0, 1, ..., n - 1, 0, ... from here on */
        t_window_start = micros32();
        acc_n = osr;
        return;
    }
    acc[ch] += v;
    if (ch + 1u < SP_N_CHANNELS || ++acc_k < acc_n)
        return;
    /* window complete: it ran from the end of the previous one to this interrupt (the same
     * interrupt latency at both ends, so the centre is unbiased) */
    uint32_t t_end = micros32();
    for (uint8_t i = 0; i < SP_N_CHANNELS; ++i) {
        done_sum[i] = acc[i];
        acc[i] = 0;
    }
    done_t_us = t_window_start + (t_end - t_window_start) / 2u;
    done_n = acc_n;
    done_seq = win_seq++;
    done_ready = 1;
    t_window_start = t_end;
    acc_k = 0;
    acc_n = osr;
}

/* ---- protocol ---- */
static const uint8_t fw[3] = {FW_MAJOR, FW_MINOR, FW_PATCH};

static void send_info(void)
{
    uint8_t payload[SP_MAX_PAYLOAD], out[SP_MAX_FRAME];
    uint16_t next_seq, n_osr;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        next_seq = done_ready ? done_seq : win_seq; /* seq of the next DATA frame */
        n_osr = osr;
    }
    size_t n = sp_pack_info(payload, next_seq, micros32(), fw, n_osr);
    uart_write(out, (uint8_t)sp_frame(payload, n, out));
}

static uint8_t cmd_body[SP_MAX_FRAME];
static uint8_t cmd_len;
static uint8_t cmd_overlong; /* a body longer than any command: drop it at its delimiter */

static void poll_commands(void)
{
    int c;
    while ((c = uart_getc()) >= 0) {
        if (c != 0) {
            if (cmd_len < sizeof cmd_body)
                cmd_body[cmd_len++] = (uint8_t)c;
            else
                cmd_overlong = 1;
            continue;
        }
        uint8_t payload[SP_MAX_PAYLOAD];
        int len = cmd_overlong ? -1 : sp_unframe(cmd_body, cmd_len, payload, sizeof payload);
        cmd_len = 0;
        cmd_overlong = 0;
        if (len < 2 || payload[0] < SP_PROTOCOL_VERSION_MIN || payload[0] > SP_PROTOCOL_VERSION)
            continue;
        if (payload[1] == SP_CMD_SET_OSR && len == 4) {
            uint16_t n = sp_get_u16(payload + 2);
            if (n >= 1u && n <= OSR_MAX)
                ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { osr = n; } /* from the next window on */
            send_info(); /* the INFO frame tells the host which N is in force */
        } else if (payload[1] == SP_CMD_GET_INFO && len == 2) {
            send_info();
        }
    }
}

int main(void)
{
    TCCR1A = 0;
    TCCR1B = _BV(CS11); /* clk/8: 0.5 us per tick */
    TIMSK1 = _BV(TOIE1);
    uart_init();
    sei();
    send_info(); /* after a reset the board clock restarts near 0: the host counts a restart */
    adc_init();

    uint8_t payload[SP_MAX_PAYLOAD], out[SP_MAX_FRAME];
    uint32_t sum[SP_N_CHANNELS];
    for (;;) {
        if (done_ready) {
            uint32_t t_us;
            uint16_t n, s;
            ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
            {
                for (uint8_t i = 0; i < SP_N_CHANNELS; ++i)
                    sum[i] = done_sum[i];
                t_us = done_t_us;
                n = done_n;
                s = done_seq;
                done_ready = 0;
            }
            size_t len = sp_pack_data(payload, s, t_us, n, sum);
            uart_write(out, (uint8_t)sp_frame(payload, len, out));
        }
        poll_commands();
    }
}
