"""Firmware: the C frame encoder (firmware/frame.c) against the Python protocol, byte for byte,
the AVR builds' flash/RAM use on the ATmega328P (UNO) and ATmega2560 (Mega), and the channel
counts each board's build accepts."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from softphantom.sensing.protocol import (
    DataFrame,
    FrameError,
    StreamDecoder,
    crc16,
    decode_body,
    encode_data,
    encode_info,
    encode_set_osr,
)

FW = Path(__file__).resolve().parents[1] / "firmware"


@pytest.fixture(scope="module")
def tool(tmp_path_factory):
    if shutil.which("gcc") is None:
        pytest.skip("gcc not installed (scripts/install-system-deps.sh)")
    exe = tmp_path_factory.mktemp("fw") / "frame_tool"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", str(FW / "frame.c"),
                    str(FW / "host" / "frame_tool.c"), "-o", str(exe)], check=True)
    return lambda *args: subprocess.run([str(exe), *map(str, args)], check=True, capture_output=True,
                                        text=True).stdout.strip()


def _cases():
    rng = np.random.default_rng(2024)
    yield 0, 0, 1, [0, 0, 0, 0, 0]                       # many zero bytes: COBS's worst pattern
    yield 65535, 2**32 - 1, 500, [1023 * 500] * 5          # field maxima
    yield 1, 1000, 100, [51150, 51150, 51150, 51150, 4046]
    yield 256, 0x00FF00FF, 500, [0xFF, 0xFF00, 0x07CE00, 0x010001, 0x070100]   # zero bytes in every place
    for _ in range(8):                     # sums within 0..1023·osr: the decoder's content check
        osr = int(rng.integers(1, 501))
        yield (int(rng.integers(0, 65536)), int(rng.integers(0, 2**32)), osr,
               [int(v) for v in rng.integers(0, 1023 * osr + 1, 5)])


def test_crc_check_value_both_sides(tool):
    assert tool("crc", "123456789") == "29b1" == f"{crc16(b'123456789'):04x}"


@pytest.mark.parametrize("case", list(_cases()))
def test_golden_frames_c_to_python_and_back(tool, case):
    seq, t_us, osr, raw = case
    c_frame = bytes.fromhex(tool("data", seq, t_us, osr, *raw))
    assert c_frame == encode_data(seq, t_us, osr, raw)            # C encoder == Python encoder (v2)
    assert c_frame[0] == 0 and 0 not in c_frame[1:-1] and c_frame[-1] == 0
    assert decode_body(c_frame[1:-1]) == DataFrame(seq, t_us, osr, tuple(raw))
    for version in (1, 2):                                         # Python frame → C decoder
        py_body = encode_data(seq, t_us, osr, raw, version=version).strip(b"\x00").hex()
        assert tool("decode", py_body) == (f"version {version} type 1 len 30 seq {seq} t_us {t_us} osr {osr} raw "
                                           + " ".join(map(str, raw)))


def test_c_decoder_rejects_corruption_and_reads_commands(tool):
    body = bytearray(encode_data(5, 123, 100, [1, 2, 3, 4, 5])[1:-1])
    body[10] ^= 0x04                                             # one bit flipped in a sum
    assert tool("decode", body.hex()) == "error crc"
    assert tool("decode", encode_data(5, 123, 100, [1, 2, 3, 4, 5])[1:-3].hex()) in ("error crc", "error cobs")
    # the firmware reads commands of both versions (main.c accepts payload[0] in 1..2)
    assert tool("decode", encode_set_osr(25, version=1)[:-1].hex()) == "version 1 type 16 len 4 osr 25"
    assert tool("decode", encode_set_osr(25)[1:-1].hex()) == "version 2 type 16 len 4 osr 25"
    info = bytes.fromhex(tool("info", 0, 42, 2, 0, 0, 100))
    assert info == encode_info(0, 42, (2, 0, 0), 5, 100)
    frames = StreamDecoder().feed(info)
    assert frames[0].firmware_str == "2.0.0" and frames[0].osr == 100


def test_firmware_version_and_accepted_command_versions_match_the_host():
    import re

    from softphantom.sensing.protocol import PROTOCOL_VERSION, SUPPORTED_VERSIONS
    from softphantom.virtual.board import FIRMWARE

    h = (FW / "frame.h").read_text()
    m = (FW / "main.c").read_text()
    assert int(re.search(r"SP_PROTOCOL_VERSION (\d+)u", h).group(1)) == PROTOCOL_VERSION
    assert int(re.search(r"SP_PROTOCOL_VERSION_MIN (\d+)u", h).group(1)) == min(SUPPORTED_VERSIONS)
    assert int(re.search(r"#define FW_MAJOR (\d+)", m).group(1)) == PROTOCOL_VERSION == FIRMWARE[0]


def test_firmware_fits_the_atmega328p(tmp_path, record_property):
    if shutil.which("avr-gcc") is None or shutil.which("avr-size") is None:
        pytest.skip("avr-gcc/avr-size not installed: run scripts/install-system-deps.sh (gcc-avr, avr-libc, binutils-avr)")
    elf = tmp_path / "bip_sensing.elf"
    subprocess.run(["avr-gcc", "-mmcu=atmega328p", "-DF_CPU=16000000UL", "-Os", "-std=c99", "-Wall",
                    "-Wextra", "-Werror", "-ffunction-sections", "-fdata-sections", "-Wl,--gc-sections",
                    str(FW / "main.c"), str(FW / "frame.c"), "-o", str(elf)], check=True)
    out = subprocess.run(["avr-size", str(elf)], check=True, capture_output=True, text=True).stdout
    text, data, bss = (int(v) for v in out.splitlines()[1].split()[:3])
    flash, ram = text + data, data + bss
    record_property("flash_bytes", flash)
    record_property("ram_bytes", ram)
    print(f"\nATmega328P: flash {flash} B of 32768 ({flash / 32768:.1%}), static RAM {ram} B of 2048")
    assert flash <= 32 * 1024 - 512, f"flash {flash} B exceeds 32 KiB minus the 512 B bootloader"
    assert ram <= 2048 - 512, f"static RAM {ram} B leaves under 512 B of the 2 KiB for the stack"


@pytest.fixture(scope="module")
def tool6(tmp_path_factory):
    """frame.c built for a board of 6 channels (5 arms and the urethra)."""
    if shutil.which("gcc") is None:
        pytest.skip("gcc not installed (scripts/install-system-deps.sh)")
    exe = tmp_path_factory.mktemp("fw6") / "frame_tool"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-DSP_N_CHANNELS=6u", str(FW / "frame.c"),
                    str(FW / "host" / "frame_tool.c"), "-o", str(exe)], check=True)
    return lambda *args: subprocess.run([str(exe), *map(str, args)], check=True, capture_output=True,
                                        text=True).stdout.strip()


def test_a_board_of_six_channels_speaks_the_same_frames_on_both_sides(tool6):
    # the channel count is the firmware's, fixed at build time: C and Python agree byte for byte,
    # a decoder made for 5 channels rejects a 6-channel frame by its length and the other way round
    raw = [0, 1023 * 500, 0xFF00, 7, 0x010001, 51150]
    c_frame = bytes.fromhex(tool6("data", 65535, 2**32 - 1, 500, *raw))
    assert c_frame == encode_data(65535, 2**32 - 1, 500, raw) and len(c_frame) == 39
    assert decode_body(c_frame[1:-1], n_channels=6) == DataFrame(65535, 2**32 - 1, 500, tuple(raw))
    assert tool6("decode", c_frame[1:-1].hex()) == ("version 2 type 1 len 34 seq 65535 t_us 4294967295 osr 500 raw "
                                                    + " ".join(map(str, raw)))
    info = bytes.fromhex(tool6("info", 0, 42, 2, 0, 0, 100))
    assert info == encode_info(0, 42, (2, 0, 0), 6, 100)
    dec6, dec5 = StreamDecoder(6), StreamDecoder()
    stream = info + c_frame + encode_data(0, 5200, 100, [1, 2, 3, 4, 5])
    assert [type(f).__name__ for f in dec6.feed(stream)] == ["InfoFrame", "DataFrame"]
    assert dec6.stats.malformed == 1                      # the 5-channel frame: another length
    first = encode_data(0, 0, 100, [5, 4, 3, 2, 1])  # in sync first: what follows counts as errors
    assert [f.raw for f in dec5.feed(first + stream[:-35] + encode_data(1, 52_000, 100, [1, 2, 3, 4, 5]))] == [
        (5, 4, 3, 2, 1), (1, 2, 3, 4, 5)]
    assert dec5.stats.content_errors == 1 and dec5.stats.malformed == 1  # INFO of 6 channels; the 6-channel frame
    with pytest.raises(FrameError, match="INFO n_channels 6, expected 5"):
        decode_body(info[1:-1])


def test_the_uno_builds_for_up_to_six_channels_and_the_mega_refuses_seventeen(tmp_path):
    if shutil.which("avr-gcc") is None:
        pytest.skip("avr-gcc not installed: run scripts/install-system-deps.sh (gcc-avr, avr-libc, binutils-avr)")

    def build(n):
        return subprocess.run(["avr-gcc", "-mmcu=atmega328p", "-DF_CPU=16000000UL", f"-DSP_N_CHANNELS={n}u", "-Os",
                               "-std=c99", "-Wall", "-Wextra", "-Werror", str(FW / "main.c"), str(FW / "frame.c"),
                               "-o", str(tmp_path / f"fw{n}.elf")], capture_output=True, text=True)

    assert build(6).returncode == 0
    r = build(7)
    assert r.returncode != 0 and "the Arduino UNO has 6 analog inputs (A0-A5)" in r.stderr
    r = subprocess.run(["avr-gcc", "-mmcu=atmega2560", "-DF_CPU=16000000UL", "-DSP_N_CHANNELS=17u", "-Os", "-std=c99",
                        str(FW / "main.c"), str(FW / "frame.c"), "-o", str(tmp_path / "fw17.elf")],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "the Arduino Mega 2560 has 16 analog inputs (A0-A15)" in r.stderr


def _make(tmp_path, *args):
    if shutil.which("make") is None:
        pytest.skip("make not installed")
    return subprocess.run(["make", "-s", "-C", str(FW), f"BUILD={tmp_path / 'b'}", *args], capture_output=True,
                          text=True)


@pytest.mark.parametrize("n", [9, 16])
def test_the_mega_builds_for_nine_and_sixteen_channels_and_fits(tmp_path, n, record_property):
    if shutil.which("avr-gcc") is None or shutil.which("avr-size") is None:
        pytest.skip("avr-gcc/avr-size not installed: run scripts/install-system-deps.sh (gcc-avr, avr-libc, binutils-avr)")
    r = _make(tmp_path, "BOARD=mega", f"N_CHANNELS={n}")
    assert r.returncode == 0, r.stderr
    elf = (tmp_path / "b" / "bip_sensing.elf").read_bytes()
    e_machine, e_flags = int.from_bytes(elf[18:20], "little"), int.from_bytes(elf[36:40], "little")
    assert e_machine == 83 and e_flags & 0x7F == 6          # EM_AVR, avr6: the ATmega2560's architecture
    assert (tmp_path / "b" / "bip_sensing.hex").stat().st_size > 0
    text, data, bss = (int(v) for v in r.stdout.splitlines()[1].split()[:3])    # make prints avr-size
    record_property("flash_bytes", text + data)
    record_property("ram_bytes", data + bss)
    assert text + data <= 256 * 1024 - 8 * 1024           # the Mega's stk500v2 bootloader takes 8 KiB
    assert data + bss <= 8192 - 1024


@pytest.mark.parametrize("board, n, message", [
    ("uno", 7, "N_CHANNELS=7: the Arduino UNO has 6 analog inputs (A0-A5), so BOARD=uno reads 2..6 channels; "
               "BOARD=mega reads up to 16"),
    ("mega", 17, "N_CHANNELS=17: the Arduino Mega 2560 has 16 analog inputs (A0-A15), so BOARD=mega reads 2..16 "
                 "channels"),
    ("mega", 1, "N_CHANNELS=1: the Arduino Mega 2560 has 16 analog inputs"),
    ("due", 5, "BOARD=due: a board is uno (ATmega328P, 6 analog inputs) or mega (ATmega2560, 16)"),
])
def test_make_refuses_a_channel_count_the_board_cannot_read_in_one_line(tmp_path, board, n, message):
    r = _make(tmp_path, f"BOARD={board}", f"N_CHANNELS={n}")
    lines = r.stderr.strip().splitlines()
    assert r.returncode != 0 and len(lines) == 1 and message in lines[0], r.stderr
    assert not (tmp_path / "b").exists()                  # refused before anything is built


def test_a_build_directory_follows_its_board_and_channel_count(tmp_path):
    # the same BUILD for another board or n is rebuilt (BUILD/config), never a stale .elf of the other
    if shutil.which("avr-gcc") is None:
        pytest.skip("avr-gcc not installed: run scripts/install-system-deps.sh (gcc-avr, avr-libc, binutils-avr)")
    elf = tmp_path / "b" / "bip_sensing.elf"
    config = None
    for board, mcu, n, arch in (("uno", "atmega328p", 5, 5), ("mega", "atmega2560", 9, 6),
                                ("mega", "atmega2560", 9, 6), ("uno", "atmega328p", 6, 5)):
        before = elf.stat().st_mtime_ns if elf.exists() else None
        assert _make(tmp_path, f"BOARD={board}", f"N_CHANNELS={n}").returncode == 0
        assert int.from_bytes(elf.read_bytes()[36:40], "little") & 0x7F == arch
        assert (elf.stat().st_mtime_ns == before) == (config == (board, n))  # rebuilt only when it changed
        config = (board, n)
        assert (tmp_path / "b" / "config").read_text().split()[:3] == [f"BOARD={board}", f"MCU={mcu}", f"N_CHANNELS={n}"]
