"""Timing of the Arduino UNO board (ATmega328P at 16 MHz): frame rate for a given OSR, UART load.

One ADC conversion takes 13 ADC clocks; at prescaler 128 the ADC clock is 125 kHz, so 104 µs.
The board converts 5 channels × N readings per frame, round-robin. Derivation: docs/protocol.md.
"""

from __future__ import annotations

from softphantom.errors import UserError

F_CPU_HZ = 16_000_000
ADC_CYCLES_PER_CONVERSION = 13
N_CHANNELS = 5
OSR_MIN, OSR_MAX = 1, 500
"""OSR range the firmware accepts: at 500 a frame of the BIP's 5 channels takes 0.26 s, inside the
host's 0.5 s silence limit; of a Mega's 16, 0.83 s (the host then waits two frame periods)."""


def conversion_time_s(prescaler: int = 128, f_cpu_Hz: float = F_CPU_HZ) -> float:
    """Time of one ADC conversion.

    >>> round(conversion_time_s() * 1e6)
    104
    """
    return ADC_CYCLES_PER_CONVERSION * prescaler / f_cpu_Hz


def frame_rate_Hz(osr: int, prescaler: int = 128, n_channels: int = N_CHANNELS,
                  f_cpu_Hz: float = F_CPU_HZ) -> float:
    """Frames per second when the board sums ``osr`` readings of each channel (ADC-bound).

    >>> round(frame_rate_Hz(100), 1), round(frame_rate_Hz(25), 1)   # the "19.2 Hz and 77 Hz modes"
    (19.2, 76.9)
    """
    if not OSR_MIN <= int(osr) <= 65535:
        raise UserError(f"osr must be 1..65535, got {osr}")
    return 1.0 / (n_channels * int(osr) * conversion_time_s(prescaler, f_cpu_Hz))


def uart_bytes_per_s(baud: int = 115_200) -> float:
    """UART payload capacity: 10 bits per byte (start, 8 data, stop).

    >>> uart_bytes_per_s()
    11520.0
    """
    return baud / 10.0


def uart_load(frame_bytes: int, osr: int, baud: int = 115_200, prescaler: int = 128) -> float:
    """Fraction of the UART's capacity the data frames use at the ADC-bound frame rate.

    >>> round(uart_load(34, 1), 1)     # OSR 1 (1.9 kHz frames) would overrun 115200 baud
    5.7
    >>> round(uart_load(34, 25), 3)    # the 77 Hz mode uses under a quarter of it
    0.227
    """
    return frame_bytes * frame_rate_Hz(osr, prescaler) / uart_bytes_per_s(baud)
