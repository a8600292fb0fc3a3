"""NVIDIA GPUs on this machine, seen by the device files their driver makes (/dev/nvidia0, ...): no CUDA call,
so a process that forks workers may ask (CUDA started before a fork is unusable in the children)."""

from __future__ import annotations

import glob

NVIDIA_DEVICE_NODES = "/dev/nvidia[0-9]*"  # one per GPU (nvidiactl and nvidia-uvm are the driver's own)


def nvidia_gpus() -> list[str]:
    """The GPUs' device files, sorted; empty on a machine without an NVIDIA driver."""
    return sorted(glob.glob(NVIDIA_DEVICE_NODES))
