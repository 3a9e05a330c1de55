"""The machine a trial runs on, as far as its numbers depend on it.

A trial is bit-exact on one machine at one number of torch threads (a re-run in a fresh
process gives the same curve; more threads split a sum into other parts), not across
machines: PyTorch's CPU kernels are chosen at run time, ATen's vectorised
loops by the instruction set it detects and MKL's matrix products by the CPU's vendor as
well. Measured on fetch_reach_cpu's ``state/0/0`` (MLPs only, so MKL's products are the
only kernels that matter there): on an AMD EPYC its step-0 final distance is 0.1777445,
and 0.1777456 with ``MKL_CBWR=COMPATIBLE``, MKL's vendor-neutral path; the study recorded
0.1777448 on the machine it ran on; by step 7,000 the success rates differ (0.1 and 0.3).
So every run of a trial records ``describe(device)``, and a re-run is expected to give the
recorded curve where the description is the same.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

import torch

CPUINFO = Path("/proc/cpuinfo")

#: the conv layout by CPU vendor, measured with benchmarks/bench_update_speed.py (both
#: layouts, every row, quiet machine; docs/speed.md): channels-last (oneDNN's blocked
#: convolutions) is faster in every row on an Intel Xeon with AMX (1.1-2x) and on an AMD
#: EPYC Zen 4 (1.1-1.7x). Chosen by vendor, not by a start-up timing, so that a trial's
#: numbers (the layout changes the order of floating-point sums) do not depend on a noisy
#: measurement; a vendor not measured keeps PyTorch's default.
CONV_LAYOUTS = {"GenuineIntel": "channels_last", "AuthenticAMD": "channels_last"}


def cpu_fields(cpuinfo: str) -> dict[str, str]:
    """The first processor's ``vendor_id``, ``cpu family``, ``model`` and ``model name``
    in ``/proc/cpuinfo`` text (what MKL dispatches on besides the instruction set)."""
    fields: dict[str, str] = {}
    for line in cpuinfo.split("\n\n", 1)[0].splitlines():
        name, _, value = line.partition(":")
        fields.setdefault(name.strip(), value.strip())
    return {k: fields[k] for k in ("vendor_id", "cpu family", "model", "model name") if k in fields}


def _cpuinfo() -> str:
    try:
        return CPUINFO.read_text()
    except OSError:  # not Linux: what the platform module knows
        return ""


def _cpu() -> dict[str, str]:
    return cpu_fields(_cpuinfo())


def cpu_id(cpu: dict[str, str] | None = None) -> str:
    """The CPU as a trial's record names it (``describe``'s ``cpu``): vendor, family, model
    (of ``cpu``, ``cpu_fields``' answer, read here when not given)."""
    cpu = _cpu() if cpu is None else cpu
    ids = [cpu.get("vendor_id", platform.machine()), cpu.get("cpu family"), cpu.get("model")]
    return " ".join(i for i in ids if i)


def native_bf16() -> list[str]:
    """The CPU's native bf16 instructions among AMX-BF16 and AVX512-BF16 (the flags
    ``/proc/cpuinfo`` lists; empty: bf16 is emulated, slower than fp32)."""
    flags = next((line.split(":", 1)[1].split() for line in _cpuinfo().splitlines()
                  if line.startswith("flags")), [])  # fmt: skip
    return [flag for flag in ("amx_bf16", "avx512_bf16") if flag in flags]


#: names a layout (``channels_last`` or ``nchw``) that replaces the one chosen here
LAYOUT_VARIABLE = "GCRL_CONV_LAYOUT"


def conv_layout(device: torch.device) -> str:
    """The layout the agent's convolutions run in here: ``GCRL_CONV_LAYOUT`` when set,
    else ``channels_last`` on CUDA and where ``CONV_LAYOUTS`` says so, else ``nchw``
    (PyTorch's default)."""
    forced = os.environ.get(LAYOUT_VARIABLE)
    if forced:
        if forced not in ("channels_last", "nchw"):
            raise ValueError(f"{LAYOUT_VARIABLE} must be channels_last or nchw, got {forced!r}")
        return forced
    if device.type == "cuda":
        return "channels_last"
    return CONV_LAYOUTS.get(_cpu().get("vendor_id", ""), "nchw")


def describe(device: torch.device) -> dict[str, str]:
    """What a trial's numbers depend on beyond its code and config: the CPU (``cpu``:
    vendor, family and model number; ``cpu_name``), the instruction set of PyTorch's
    kernels, PyTorch's version, the conv layout (``conv_layout``), the torch threads it
    runs with now (``threads``; a launch's ``--threads-per-trial`` is not in the config's
    identity) and, on CUDA, the GPU."""
    cpu = _cpu()
    described = {
        "cpu": cpu_id(cpu),
        "cpu_name": cpu.get("model name", platform.processor()),
        "kernels": torch.backends.cpu.get_cpu_capability(),
        "torch": str(torch.__version__),  # a str subclass that torch.load refuses
        "conv_layout": conv_layout(device),
        "threads": str(torch.get_num_threads()),
    }
    if device.type == "cuda":
        described["gpu"] = torch.cuda.get_device_name(device)
    return described
