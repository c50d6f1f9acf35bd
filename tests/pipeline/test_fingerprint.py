"""Code fingerprints: comments and docstrings do not count; helpers and constants do."""
import textwrap

import pytest

from pipeline.errors import PipelineError
from pipeline.fingerprint import Fingerprinter

MOD = '''\
"""Module docstring."""
import numpy as np
from pkg import util
from pkg.util import helper as h
import pkg.other as other

SCALE = 2.0


def _inner(x):
    return x * SCALE


def node(x):
    """Docstring."""
    # comment
    return h(_inner(x)) + util.offset() + other.CONST


def unrelated(x):
    return x - 1
'''

UTIL = '''\
def helper(x):
    return x + 1


def offset():
    return 3


def unused():
    return 0
'''

OTHER = "CONST = 5\nNOT_USED = 6\n"


def make(tmp_path, mod=MOD, util=UTIL, other=OTHER):
    pkg = tmp_path / "pkg"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "mod.py").write_text(mod)
    (pkg / "util.py").write_text(util)
    (pkg / "other.py").write_text(other)
    return Fingerprinter([tmp_path]).fingerprint("pkg.mod:node")


def test_pinned(tmp_path):
    assert make(tmp_path) == "ddd3a67adc90f93f"


def test_comments_docstrings_formatting_do_not_count(tmp_path):
    fp = make(tmp_path)
    edited = MOD.replace("# comment", "# another comment\n    # two").replace('"""Docstring."""', '"""Other."""')
    edited = edited.replace("return x * SCALE", "return (x *\n            SCALE)  # why")
    assert make(tmp_path, mod=edited) == fp


@pytest.mark.parametrize("where,old,new", [
    ("mod", "SCALE = 2.0", "SCALE = 3.0"),                  # a constant used by a helper
    ("mod", "return x * SCALE", "return x / SCALE"),       # a same-module helper
    ("util", "return x + 1", "return x + 2"),              # an imported helper (from-import alias)
    ("util", "return 3", "return 4"),                      # module attribute use
    ("other", "CONST = 5", "CONST = 7"),                   # `import a.b as c` attribute
])
def test_dependency_edits_change_fingerprint(tmp_path, where, old, new):
    fp = make(tmp_path)
    files = {"mod": MOD, "util": UTIL, "other": OTHER}
    assert old in files[where]
    files[where] = files[where].replace(old, new)
    assert make(tmp_path, **files) != fp


@pytest.mark.parametrize("where,old,new", [
    ("mod", "return x - 1", "return x - 2"),               # another node's function
    ("util", "return 0", "return 9"),                      # unused helper in a used module
    ("other", "NOT_USED = 6", "NOT_USED = 8"),
])
def test_unrelated_edits_do_not_change_fingerprint(tmp_path, where, old, new):
    fp = make(tmp_path)
    files = {"mod": MOD, "util": UTIL, "other": OTHER}
    files[where] = files[where].replace(old, new)
    assert make(tmp_path, **files) == fp


def test_missing_function_is_a_clear_error(tmp_path):
    make(tmp_path)
    with pytest.raises(PipelineError, match="defines no 'nope'"):
        Fingerprinter([tmp_path]).fingerprint("pkg.mod:nope")
    with pytest.raises(PipelineError, match="cannot find module 'pkg.absent'"):
        Fingerprinter([tmp_path]).fingerprint("pkg.absent:f")


def test_files_lists_dependency_modules(tmp_path):
    make(tmp_path)
    files = Fingerprinter([tmp_path]).files("pkg.mod:node")
    assert [f.rsplit("/", 1)[-1] for f in files] == ["mod.py", "other.py", "util.py"]
