"""Code fingerprints: comments and docstrings do not count; helpers and constants do."""

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
    assert make(tmp_path) == "c01dec97d3bb6c51"


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


HELPERS = "def h1(x):\n    return x + 1\n\n\ndef other(x):\n    return x\n"

# each case: a node module using pkg.helpers.h1 in one of the ways Python allows
USAGES = {
    "local import": "def node(x):\n    from pkg.helpers import h1\n    return h1(x)\n",
    "star import": "from pkg.helpers import *\n\n\ndef node(x):\n    return h1(x)\n",
    "try import": ("try:\n    from pkg.helpers import h1\nexcept ImportError:\n    h1 = None\n\n\n"
                   "def node(x):\n    return h1(x)\n"),
    "def under if": ("import sys\nif sys.version_info > (3,):\n    from pkg.helpers import h1\n\n"
                     "    def node(x):\n        return h1(x)\n"),
    "dotted chain": "import pkg.sub.deep\n\n\ndef node(x):\n    return pkg.sub.deep.g(x)\n",
    "module as value": "from pkg import helpers\n\n\ndef node(x):\n    return getattr(helpers, 'h1')(x)\n",
    "relative import": "from .helpers import h1\n\n\ndef node(x):\n    return h1(x)\n",
    "registry statement": ("from pkg.helpers import h1\nREG = {}\nREG.update(scale=1)\n\n\n"
                           "def node(x):\n    return h1(x) * REG['scale']\n"),
}


def _fp(tmp_path, mod, helpers=HELPERS, deep="def g(x):\n    return x * 2\n", reg="REG.update(scale=1)"):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True, exist_ok=True)
    for f, text in {"__init__.py": "", "sub/__init__.py": "", "helpers.py": helpers,
                    "sub/deep.py": deep, "mod.py": mod.replace("REG.update(scale=1)", reg)}.items():
        (pkg / f).write_text(text)
    return Fingerprinter([tmp_path]).fingerprint("pkg.mod:node")


@pytest.mark.parametrize("usage", list(USAGES))
def test_every_way_of_using_a_helper_is_followed(tmp_path, usage):
    mod = USAGES[usage]
    fp = _fp(tmp_path, mod)
    if usage == "dotted chain":
        assert _fp(tmp_path, mod, deep="def g(x):\n    return x * 3\n") != fp
    elif usage == "registry statement":
        assert _fp(tmp_path, mod, reg="REG.update(scale=2)") != fp
    else:
        assert _fp(tmp_path, mod, helpers=HELPERS.replace("x + 1", "x + 2")) != fp
    assert _fp(tmp_path, mod) == fp  # and deterministic
