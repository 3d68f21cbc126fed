"""What a benchmark ran on, printed at the top of every benchmark's output."""

from __future__ import annotations

import os
import platform
import sys

import numpy as np


def describe() -> str:
    model = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem = ""
    try:
        with open("/proc/meminfo", encoding="utf-8") as f:
            kib = int(f.readline().split()[1])
            mem = f", {kib / 2**20:.1f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    return (
        f"machine: {model}, {os.cpu_count()} cores{mem}; {platform.system()} {platform.release()}; "
        f"Python {sys.version.split()[0]}, numpy {np.__version__}"
    )
