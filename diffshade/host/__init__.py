"""host: plumbing: compiled CPU kernels (numba), their XLA FFI binding, process tuning.

No public face: nothing outside diffshade calls these modules. The package imports none
of them, so that diffshade/__init__ imports host.cputune, and applies it, before anything
else of diffshade loads.
"""
