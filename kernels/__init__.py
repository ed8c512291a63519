"""Warp device code: ``@wp.struct``, ``@wp.func`` and ``@wp.kernel`` definitions only.

Nothing here touches files or holds state; host classes in :mod:`orthowarp` pack their
float64 parameters into the structs defined here, and :mod:`orthowarp.pipeline` launches the
kernels.
"""
