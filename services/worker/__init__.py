"""worker service.

Its compiled kernels are built for one x86-64 level on every machine that has it (kernel_target): chosen here,
before any kernel module of the package loads.
"""

from services.worker import kernel_target

kernel_target.select()
