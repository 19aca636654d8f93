"""The fault components' firing line has one definition (harness/firing.py)."""

import pytest

from cloneguard.harness import firing


def test_a_line_reads_back_as_written():
    text = "noise\n" + firing.line("segfault-gil-held", 1795800000123456789, 4242).decode() + "more noise\n"
    assert list(firing.parse(text)) == [("segfault-gil-held", 1795800000123456789, 4242)]


def test_a_line_cut_short_or_garbled_is_not_read():
    whole = firing.line("abort", 17, 99).decode()
    assert list(firing.parse(whole[:-8])) == []
    assert list(firing.parse("x" + whole)) == []


def test_a_fault_name_is_one_word():
    with pytest.raises(ValueError):
        firing.line("two words", 1, 1)
