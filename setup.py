"""The one compiled part: shm://'s ring end (``uniros_async/transports/_shm_ring_c.c``); everything else is in
pyproject.toml. ``optional=True``: where no C compiler is at hand the install still succeeds and shm:// uses the
pure-Python ``RingEnd`` (``python -m uniros_async.transports._shm_ring`` says which one is in use)."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "uniros_async.transports._shm_ring_c",
            ["uniros_async/transports/_shm_ring_c.c"],
            extra_compile_args=["-O2", "-Wall", "-Wextra", "-Wno-missing-field-initializers"],
            optional=True,
        )
    ]
)
