"""Building the package's C sources into shared libraries, once per source, compiler and CPU.

A source is compiled with ``cc -O3 -march=native -fopenmp`` (``CC`` picks the compiler; without
OpenMP or ``-march=native`` where those fail) into ``$BSMS_CACHE/native`` (default
``~/.cache/bsms/native``), under a temporary name and then renamed, so concurrent first uses
never see half a file. ``BSMS_NATIVE=0`` turns every compiled path off. Callers keep a pure
Python/torch path for when :func:`build` returns None; the tests compare the two.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

__all__ = ["FLAGS", "cache_dir", "build", "cpu_summary"]

FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-fPIC", "-shared", "-fopenmp")


def cache_dir() -> Path:
    """Where compiled libraries are kept: ``$BSMS_CACHE/native`` or ``~/.cache/bsms/native``."""
    root = os.environ.get("BSMS_CACHE") or Path.home() / ".cache" / "bsms"
    return Path(root) / "native"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("model name", "flags")):
                return line
    except OSError:
        pass
    return platform.processor()


def cpu_summary() -> str:
    """The CPU in words, with the vector extensions a speed figure depends on, e.g. ``AMD EPYC 7B13,
    AVX2, no AVX-512`` (``AVX-512 with BF16`` where it has bf16 dot products)."""
    name, flags = platform.processor() or platform.machine(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and ":" in line:
                name = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and ":" in line:
                flags = set(line.split(":", 1)[1].split())
            if flags and name:
                break
    except OSError:
        return name
    if not flags:
        return name
    wide = "no AVX-512" if "avx512f" not in flags else (
        "AVX-512 with BF16" if "avx512_bf16" in flags else "AVX-512")
    return f"{name}, {'AVX2' if 'avx2' in flags else 'no AVX2'}, {wide}"


def _compile(compiler: str, source: Path, out: Path, defines: tuple[str, ...] = ()) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        for flags in (FLAGS, tuple(f for f in FLAGS if f not in ("-fopenmp", "-march=native"))):
            done = subprocess.run([compiler, *flags, *defines, str(source), "-o", tmp, "-lm"], capture_output=True,
                                  text=True)
            if done.returncode == 0:
                os.replace(tmp, out)
                return
        raise OSError(f"{compiler} failed: {done.stderr.strip()[-500:]}")
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def build(source: Path, what: str, fallback: str, depends: tuple[Path, ...] = (),
          defines: tuple[str, ...] = ()) -> ctypes.CDLL | None:
    """The library of ``source``, compiled into :func:`cache_dir` on first use, or None where it
    cannot be (warning once per call site's cache: ``what`` names the compiled code, ``fallback``
    says what runs instead, e.g. "it runs in torch, several times slower"). depends: the files
    ``source`` includes, which take part in the cache key too. defines: preprocessor definitions
    (``-DNAME=VALUE``) for a variant of the source, part of the key. A source or depends file that
    cannot be read (an install without it) warns the same way and returns None."""
    if os.environ.get("BSMS_NATIVE", "1") == "0":
        return None
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        warnings.warn(f"no C compiler (cc) found: {fallback}; install gcc, or set BSMS_NATIVE=0 to silence this",
                      RuntimeWarning, stacklevel=3)
        return None
    texts = []
    for file in (source, *depends):
        try:
            texts.append(file.read_text())
        except (OSError, UnicodeDecodeError) as error:  # e.g. an install that left a header out
            reason = error.strerror if isinstance(error, OSError) and error.strerror else str(error)
            _warn(what, f"cannot read {file}: {reason}", fallback)
            return None
    key = hashlib.sha256("\n".join([*texts, compiler, " ".join((*FLAGS, *defines)), platform.machine(),
                                    _cpu_model()]).encode()).hexdigest()[:16]
    path = cache_dir() / f"{source.stem}-{key}.so"
    try:
        if not path.is_file():
            _compile(compiler, source, path, defines)
        return ctypes.CDLL(str(path))
    except OSError as error:
        _warn(what, str(error), fallback)
        return None


def _warn(what: str, reason: str, fallback: str) -> None:
    # stacklevel 4 (this function, build, the function that asked for the library): where it was asked for
    warnings.warn(f"could not build the {what} ({reason}); {fallback}. Set BSMS_NATIVE=0 to silence this",
                  RuntimeWarning, stacklevel=4)
