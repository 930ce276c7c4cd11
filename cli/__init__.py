"""The ``fleetlink`` command. Its package pins OpenBLAS's kernels before anything imports numpy, so
every command (a replay, the field and the agents it starts) computes alike on every x86-64 host
(shared/blas.py)."""

from fleetlink.shared.blas import pin_blas_kernels

pin_blas_kernels()
