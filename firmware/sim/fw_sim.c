/* Firmware in the loop: runs the sensing board's own .elf in simavr, on the MCU it is built for
 * (SIM_MCU: atmega328p, the UNO, or atmega2560, the Mega; both 16 MHz; make BOARD=uno|mega sim).
 *
 *   fw_sim FIRMWARE.elf [--vs VOLTS] [--noise CODES] [--seed N] [--log-adc]
 *
 * The host drives it in lock-step over stdin/stdout (binary, little-endian; one request, then
 * its reply, so neither side can block the other):
 *   'V' u32 n, n x (u64 cycle, N_CH x f64 volts)  voltages at the ADC inputs from that cycle
 *                                               on (linear between points, held after the last)
 *   'U' u32 n, n bytes                          bytes host -> board, sent at the wire's rate
 *   'R' u64 cycle                               run the CPU until that cycle; reply:
 *        u64 cycle, u32 n, n x (u64 cycle, u8 byte)   board -> host bytes (cycle of their UDR0 write)
 *        u32 m, m x (u64 cycle, u8 ch, u16 code)      ADC conversions started (with --log-adc)
 *   'Q'                                         quit
 * Time is the emulator's cycle count (16 cycles per us). Each conversion takes the voltage of its
 * channel at its start and quantizes it as the datasheet does, code = floor(1024 V / VS + noise)
 * clipped to 0..1023 (Gaussian noise of --noise codes sigma, seeded), ratiometric with VS.
 */
#include <elf.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "avr_adc.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"

#define F_CPU 16000000u
#ifndef N_CH
#define N_CH 5 /* the firmware's channel count (make N_CHANNELS=n sim builds both for n) */
#endif
#ifndef SIM_MCU
#define SIM_MCU "atmega328p" /* the simavr core (make BOARD=mega sim: "atmega2560") */
#endif
/* one byte on the wire: 10 bits at the firmware's 117647 baud (UBRR 16, U2X) */
#define RX_BYTE_CYCLES 1360u
#define AVCC_MV 5000u
#define ADCSRA_ADDR 0x7A /* data address, the same on the ATmega328P and ATmega2560 */
#define ADCSRB_ADDR 0x7B
#define MUX5_BIT 0x08 /* ADCSRB bit 3 on the ATmega2560: MUX5:0 = 100xxx selects ADC8..ADC15 */
#define ADATE_BIT 0x20

typedef struct {
    uint64_t cycle;
    double v[N_CH];
} point_t;

typedef struct {
    uint8_t *b;
    size_t n, cap;
} buf_t;

static avr_t *avr;
static FILE *out;
static double vs = 5.0, noise = 0.0;
static uint64_t rng_state;
static int log_adc;
static point_t *pts;
static size_t n_pts, cap_pts, i_pt;
static buf_t tx, adc_log, rx_q;
static size_t rx_pos;
static avr_irq_t *adc_irq, *uart_irq;
static uint16_t prev_code;
static int upper_bank_folded;
static int have_prev;

static void die(const char *msg)
{
    fprintf(stderr, "fw_sim: %s\n", msg);
    exit(2);
}

static void put(buf_t *b, const void *p, size_t n)
{
    if (b->n + n > b->cap) {
        b->cap = (b->n + n) * 2 + 256;
        b->b = realloc(b->b, b->cap);
        if (!b->b)
            die("out of memory");
    }
    memcpy(b->b + b->n, p, n);
    b->n += n;
}

static void read_exact(void *p, size_t n)
{
    if (fread(p, 1, n, stdin) != n)
        exit(0); /* host gone: end quietly */
}

/* splitmix64 + Box-Muller: a seeded normal deviate without any library state */
static double uniform01(void)
{
    uint64_t z = (rng_state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    z ^= z >> 31;
    return ((double)(z >> 11) + 0.5) / 9007199254740992.0;
}

static double normal(void)
{
    return sqrt(-2.0 * log(uniform01())) * cos(6.283185307179586 * uniform01());
}

static double volts_at(uint64_t cycle, unsigned ch)
{
    if (n_pts == 0)
        return 0.0;
    while (i_pt + 1 < n_pts && pts[i_pt + 1].cycle <= cycle)
        ++i_pt;
    const point_t *a = &pts[i_pt];
    if (cycle <= a->cycle || i_pt + 1 >= n_pts)
        return a->v[ch];
    const point_t *b = a + 1;
    double w = (double)(cycle - a->cycle) / (double)(b->cycle - a->cycle);
    return a->v[ch] + w * (b->v[ch] - a->v[ch]);
}

/* A conversion starts: it samples its channel's voltage now. simavr returns, when ADC is read,
 * the value last given to the channel in ADMUX at that moment, scaled as mV * 1023 / AVcc (the
 * smallest mV that scales to a code makes the reading exact). In free-running mode the result of
 * the previous conversion is read after this one has started (and latched the next channel), so
 * that result is given to this conversion's channel; in single-conversion mode its own. */
static void on_adc_start(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    union {
        avr_adc_mux_t mux;
        uint32_t v;
    } e = {.v = value};
    unsigned ch = e.mux.src;
    if (e.mux.kind != ADC_MUX_SINGLE)
        return;
    if (upper_bank_folded && (avr->data[ADCSRB_ADDR] & MUX5_BIT))
        ch += 8u; /* ADC8..15, reported as slots 0..7 (fold_upper_bank) */
    if (ch >= N_CH)
        return;
    double x = 1024.0 * volts_at(avr->cycle, ch) / vs;
    if (noise > 0)
        x += noise * normal();
    double f = floor(x);
    uint16_t code = f < 0 ? 0 : f > 1023 ? 1023 : (uint16_t)f;
    uint16_t shown = code;
    if ((avr->data[ADCSRA_ADDR] & ADATE_BIT) && have_prev)
        shown = prev_code;
    prev_code = code;
    have_prev = 1;
    uint32_t mv = ((uint32_t)shown * AVCC_MV + 1022u) / 1023u;
    avr_raise_irq(adc_irq + ADC_IRQ_ADC0 + (ch & 7u), mv);
    if (log_adc) {
        uint8_t rec[11];
        uint64_t c = avr->cycle;
        memcpy(rec, &c, 8);
        rec[8] = (uint8_t)ch;
        memcpy(rec + 9, &code, 2);
        put(&adc_log, rec, sizeof rec);
    }
}

/* simavr 1.6 holds 8 ADC input values (adc_values[8]): it ignores ADC_IRQ_ADC8..15 and, for
 * MUX5:0 = 100xxx, reads past that array. ADC8..15 (the Mega's A8-A15) are folded onto slots 0..7
 * here, which is exact because each value is given when a conversion starts (on_adc_start) and read
 * by the ADC interrupt that comes with it, long before the next start; the channel comes from MUX5. */
static void fold_upper_bank(void)
{
    for (avr_io_t *io = avr->io_port; io; io = io->next) {
        if (strcmp(io->kind, "adc"))
            continue;
        avr_adc_t *a = (avr_adc_t *)io;
        for (unsigned k = 0; k < 8; ++k) {
            avr_adc_mux_t *m = &a->muxmode[32u + k];
            if (m->kind == ADC_MUX_SINGLE && m->src == 8u + k) {
                m->src = k;
                upper_bank_folded = 1;
            }
        }
    }
}

static void on_uart_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    uint8_t rec[9];
    uint64_t c = avr->cycle;
    memcpy(rec, &c, 8);
    rec[8] = (uint8_t)value;
    put(&tx, rec, sizeof rec);
}

static int rx_armed;

/* host -> board: one byte per byte time, as the wire delivers them */
static avr_cycle_count_t rx_tick(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)param;
    if (rx_pos >= rx_q.n) {
        rx_q.n = rx_pos = 0;
        rx_armed = 0;
        return 0;
    }
    avr_raise_irq(uart_irq + UART_IRQ_INPUT, rx_q.b[rx_pos++]);
    return when + RX_BYTE_CYCLES;
}

static void add_points(uint32_t n)
{
    if (i_pt > 0) { /* drop what lies behind the current point */
        memmove(pts, pts + i_pt, (n_pts - i_pt) * sizeof *pts);
        n_pts -= i_pt;
        i_pt = 0;
    }
    if (n_pts + n > cap_pts) {
        cap_pts = (n_pts + n) * 2;
        pts = realloc(pts, cap_pts * sizeof *pts);
        if (!pts)
            die("out of memory");
    }
    for (uint32_t k = 0; k < n; ++k) {
        point_t *p = &pts[n_pts + k];
        read_exact(&p->cycle, 8);
        read_exact(p->v, sizeof p->v);
        if (n_pts + k > 0 && p->cycle <= p[-1].cycle)
            die("voltage points must have increasing cycles");
    }
    n_pts += n;
}

/* simavr 1.6 times a UART byte when UBRR0L is written (before the firmware sets U2X0, so at half
 * the speed) and counts a parity bit that 8N1 does not have: set the byte time the chip has,
 * from the registers as configured (start + 8 data [+ parity] + stop bits, UBRR, U2X). */
static void uart_fix_timing(void)
{
    for (avr_io_t *io = avr->io_port; io; io = io->next) {
        if (strcmp(io->kind, "uart") || ((avr_uart_t *)io)->name != '0')
            continue; /* the firmware's UART0 (the 2560 has three more) */
        avr_uart_t *u = (avr_uart_t *)io;
        uint8_t *d = avr->data; /* USART0's registers: the same addresses on both MCUs */
        uint32_t ubrr = d[0xC4] | ((uint32_t)(d[0xC5] & 0x0F) << 8); /* UBRR0L/H */
        uint32_t bits = 1u + 8u + ((d[0xC2] & 0x30) ? 1u : 0u) + ((d[0xC2] & 0x08) ? 2u : 1u);
        uint32_t per_bit = (ubrr + 1u) * ((d[0xC0] & 0x02) ? 8u : 16u); /* UCSR0A U2X0 */
        u->cycles_per_byte = (avr_cycle_count_t)per_bit * bits;
    }
}

static avr_cycle_count_t uart_fix_tick(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)when;
    (void)param;
    uart_fix_timing();
    return 0;
}

/* A firmware built for another MCU would run with the wrong vector table and registers: refuse it
 * by the AVR architecture avr-gcc writes in the ELF header (avr5: ATmega328P, avr6: ATmega2560). */
static void check_arch(const char *path)
{
    Elf32_Ehdr h;
    FILE *f = fopen(path, "rb");
    if (!f || fread(&h, sizeof h, 1, f) != 1 || h.e_machine != EM_AVR)
        die("cannot read the firmware .elf");
    fclose(f);
    unsigned want = strcmp(SIM_MCU, "atmega2560") ? 5u : 6u, got = h.e_flags & 0x7Fu;
    if (got != want) {
        fprintf(stderr, "fw_sim: the firmware is built for avr%u, this harness runs " SIM_MCU " (avr%u): "
                        "build both with the same make BOARD=\n", got, want);
        exit(2);
    }
}

static void run_until(uint64_t until)
{
    if (avr->cycle > 0)
        uart_fix_timing();
    while (avr->cycle < until) {
        int state = avr_run(avr);
        if (state == cpu_Done || state == cpu_Crashed)
            die("the firmware stopped (crashed or returned from main)");
    }
    uint64_t c = avr->cycle;
    uint32_t n = (uint32_t)(tx.n / 9), m = (uint32_t)(adc_log.n / 11);
    fwrite(&c, 8, 1, out);
    fwrite(&n, 4, 1, out);
    fwrite(tx.b, 1, tx.n, out);
    fwrite(&m, 4, 1, out);
    fwrite(adc_log.b, 1, adc_log.n, out);
    fflush(out);
    tx.n = adc_log.n = 0;
}

int main(int argc, char **argv)
{
    const char *elf = NULL;
    uint64_t seed = 0;
    for (int i = 1; i < argc; ++i) {
        if (!strcmp(argv[i], "--vs") && i + 1 < argc)
            vs = atof(argv[++i]);
        else if (!strcmp(argv[i], "--noise") && i + 1 < argc)
            noise = atof(argv[++i]);
        else if (!strcmp(argv[i], "--seed") && i + 1 < argc)
            seed = strtoull(argv[++i], NULL, 10);
        else if (!strcmp(argv[i], "--log-adc"))
            log_adc = 1;
        else if (!elf && argv[i][0] != '-')
            elf = argv[i];
        else
            die("usage: fw_sim FIRMWARE.elf [--vs VOLTS] [--noise CODES] [--seed N] [--log-adc]");
    }
    if (!elf || !(vs > 0) || !(noise >= 0))
        die("usage: fw_sim FIRMWARE.elf [--vs VOLTS] [--noise CODES] [--seed N] [--log-adc]");
    rng_state = seed * 0x2545F4914F6CDD1Dull + 1u;

    /* the protocol owns stdout; simavr's own messages (it printf()s) go to stderr */
    out = fdopen(dup(1), "wb");
    dup2(2, 1);

    check_arch(elf);
    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(elf, &fw))
        die("cannot read the firmware .elf");
    avr = avr_make_mcu_by_name(SIM_MCU);
    if (!avr)
        die("simavr has no " SIM_MCU " core");
    avr_init(avr);
    avr->log = LOG_ERROR;
    avr_load_firmware(avr, &fw);
    avr->frequency = F_CPU;
    avr->vcc = avr->avcc = avr->aref = AVCC_MV;

    uint32_t flags = 0; /* no console echo, no sleeping while the firmware polls */
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    adc_irq = avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, 0);
    uart_irq = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), 0);
    avr_irq_register_notify(adc_irq + ADC_IRQ_OUT_TRIGGER, on_adc_start, NULL);
    fold_upper_bank();
    avr_irq_register_notify(uart_irq + UART_IRQ_OUTPUT, on_uart_out, NULL);

    avr_cycle_timer_register(avr, F_CPU / 1000u, uart_fix_tick, NULL); /* once the UART is set up */

    for (;;) {
        uint8_t op;
        read_exact(&op, 1);
        if (op == 'V') {
            uint32_t n;
            read_exact(&n, 4);
            add_points(n);
        } else if (op == 'U') {
            uint32_t n;
            read_exact(&n, 4);
            uint8_t *tmp = malloc(n ? n : 1);
            read_exact(tmp, n);
            put(&rx_q, tmp, n);
            free(tmp);
            if (!rx_armed && n) {
                rx_armed = 1;
                avr_cycle_timer_register(avr, 1, rx_tick, NULL);
            }
        } else if (op == 'R') {
            uint64_t until;
            read_exact(&until, 8);
            run_until(until);
        } else if (op == 'Q') {
            break;
        } else {
            die("unknown request");
        }
    }
    fclose(out);
    avr_terminate(avr);
    return 0;
}
