"""datagen.compiled.build: a C source, or a file it includes, that cannot be read (an install that
left it out) is one RuntimeWarning and None, so that the caller's torch path runs, as for a
compiler that fails; nothing is compiled or cached."""

import inspect

import pytest

from datagen import compiled


def sources(folder):
    """(source, header) of a tiny library: answer() returns the header's ANSWER."""
    source, header = folder / "answer.c", folder / "answer.h"
    source.write_text('#include "answer.h"\nint answer(void) { return ANSWER; }\n')
    header.write_text("#define ANSWER 42\n")
    return source, header


@pytest.mark.parametrize("broken, reason", [
    ("missing", "No such file or directory"), ("folder", "Is a directory"), ("undecodable", "can't decode byte 0xff")])
@pytest.mark.parametrize("which", ["source", "depends"])
def test_an_unreadable_source_or_depends_file_warns_and_returns_none(tmp_path, monkeypatch, broken, reason, which):
    monkeypatch.setenv("BSMS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", "cc")  # the files are read before any compiler runs
    source, header = sources(tmp_path)
    bad = source if which == "source" else header
    bad.unlink()
    if broken == "folder":
        bad.mkdir()
    elif broken == "undecodable":
        bad.write_bytes(b"\xff\xfe int x;\n")

    def library():  # as the callers ask for their library (datagen.mpm.native.library)
        return compiled.build(source, "compiled answer", "it runs in torch, several times slower", depends=(header,))

    with pytest.warns(RuntimeWarning) as caught:
        here = inspect.currentframe().f_lineno + 1
        assert library() is None  # the warning points here, where the library was asked for
    assert len(caught) == 1
    message = str(caught[0].message)
    assert message.startswith(f"could not build the compiled answer (cannot read {bad}: ")
    assert reason in message
    assert message.endswith("); it runs in torch, several times slower. Set BSMS_NATIVE=0 to silence this")
    assert (caught[0].filename, caught[0].lineno) == (__file__, here)
    assert not (tmp_path / "cache").exists()


def test_the_same_files_readable_build_the_library(tmp_path, monkeypatch):
    monkeypatch.setenv("BSMS_CACHE", str(tmp_path / "cache"))
    source, header = sources(tmp_path)
    lib = compiled.build(source, "compiled answer", "it runs in torch", depends=(header,))
    assert lib is not None and lib.answer() == 42


def test_switched_off_it_reads_nothing_and_says_nothing(tmp_path, monkeypatch, recwarn):
    monkeypatch.setenv("BSMS_NATIVE", "0")
    assert compiled.build(tmp_path / "missing.c", "compiled answer", "it runs in torch") is None
    assert not recwarn.list
