"""bench/bench_common.cpu_description: every benchmark names the machine it ran on."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from bench_common import cpu_description  # noqa: E402

ZEN5 = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 26
model\t\t: 2
model name\t: AMD EPYC
flags\t\t: fpu sse2 avx2 avx512f avx512_bf16
processor\t: 1
cpu family\t: 26
model\t\t: 2
model name\t: AMD EPYC
"""

XEON = """vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 143
model name\t: Intel(R) Xeon(R) Processor
flags\t\t: fpu avx512f avx512_bf16 amx_bf16 amx_tile
"""


def test_a_virtual_machine_naming_only_the_line_is_told_apart_by_family_and_model() -> None:
    assert cpu_description(ZEN5) == "AMD EPYC (family 26 model 2, no AMX, AVX-512 bf16)"
    assert cpu_description(XEON) == "Intel(R) Xeon(R) Processor (family 6 model 143, AMX bf16, AVX-512 bf16)"


def test_without_flags_only_the_name_is_given() -> None:
    assert cpu_description("model name\t: Some CPU\ncpu family\t: 1\nmodel\t: 2\n") == "Some CPU"
