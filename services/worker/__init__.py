"""worker service.

Its compiled kernels are built for the best x86-64 level the machine runs (kernel_target), the same on every
machine of that level: chosen here, before any kernel module of the package loads.
"""

from services.worker.process import kernel_target

kernel_target.select()
