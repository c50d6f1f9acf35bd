"""Code fingerprints from source ASTs, without importing anything.

A node's fingerprint covers the normalised AST (no comments, docstrings or layout) of
its function and, transitively, of every project-level symbol it uses: functions,
classes and constants of its own module, and symbols imported from other modules of
the project, wherever the import statement stands. Third-party and standard-library
names are not followed. Where use cannot be resolved statically (a star import, a
module passed around as a value, a statement at module level that binds nothing) the
fingerprint takes in more than needed, never less.
"""
from __future__ import annotations

import ast
import functools
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import PipelineError

Chain = tuple[str, ...]          # `a.b.c` -> ("a", "b", "c"); a bare name -> ("a",)
Import = tuple[str, "str | None"]  # (module, symbol) or (module, None) for a module object


@dataclass
class ModuleInfo:
    name: str
    path: Path
    is_package: bool
    symbols: dict[str, str] = field(default_factory=dict)        # symbol -> own AST digest
    uses: dict[str, set[Chain]] = field(default_factory=dict)     # symbol -> name chains it uses
    local_imports: dict[str, dict[str, Import]] = field(default_factory=dict)  # imports inside it
    imports: dict[str, Import] = field(default_factory=dict)      # module-level alias -> import
    star: list[str] = field(default_factory=list)                 # `from X import *`
    preamble: str = ""          # digest of module-level statements that bind no name
    tree: ast.Module | None = field(default=None, repr=False)   # docstrings stripped

    @functools.cached_property
    def module_digest(self) -> str:
        """The whole module's digest, for a module used as a value: computed on first use
        (dumping a whole module's AST is most of the cost of parsing it)."""
        return _digest(self.tree)


def _strip_docstrings(tree: ast.AST) -> None:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]


def _digest(node: ast.AST) -> str:
    return hashlib.sha256(ast.dump(node, include_attributes=False).encode()).hexdigest()


_COMPOUND = (ast.If, ast.Try, ast.For, ast.AsyncFor, ast.While, ast.With, ast.AsyncWith, ast.Match)
if hasattr(ast, "TryStar"):
    _COMPOUND += (ast.TryStar,)


def _inner_statements(stmt: ast.stmt) -> list[ast.stmt]:
    """Statements nested in a compound statement's blocks (not inside defs)."""
    out = []
    blocks = [getattr(stmt, f, []) for f in ("body", "orelse", "finalbody")]
    blocks += [h.body for h in getattr(stmt, "handlers", [])]
    blocks += [c.body for c in getattr(stmt, "cases", [])]
    for block in blocks:
        for s in block:
            out += [s, *(_inner_statements(s) if isinstance(s, _COMPOUND) else [])]
    return out


def _bound_names(stmt: ast.stmt) -> list[str]:
    if isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [stmt.name]
    targets: list[ast.expr] = []
    if isinstance(stmt, ast.Assign):
        targets = stmt.targets
    elif isinstance(stmt, (ast.AnnAssign, ast.AugAssign)):
        targets = [stmt.target]
    elif isinstance(stmt, (ast.For, ast.AsyncFor)):
        targets = [stmt.target]
    elif isinstance(stmt, (ast.With, ast.AsyncWith)):
        targets = [i.optional_vars for i in stmt.items if i.optional_vars is not None]
    names = []
    for t in targets:
        names += [n.id for n in ast.walk(t) if isinstance(n, ast.Name)]
    return names


class _Uses(ast.NodeVisitor):
    """Maximal attribute chains and bare names used, plus import statements met."""

    def __init__(self):
        self.chains: set[Chain] = set()
        self.imports: list[ast.stmt] = []

    def visit_Attribute(self, node: ast.Attribute):
        attrs = []
        cur: ast.expr = node
        while isinstance(cur, ast.Attribute):
            attrs.append(cur.attr)
            cur = cur.value
        if isinstance(cur, ast.Name):
            self.chains.add((cur.id, *reversed(attrs)))
        else:
            self.visit(cur)

    def visit_Name(self, node: ast.Name):
        self.chains.add((node.id,))

    def visit_Import(self, node):
        self.imports.append(node)

    visit_ImportFrom = visit_Import


def _resolve_relative(module: str, is_package: bool, level: int, target: str | None) -> str:
    parts = module.split(".")
    base = parts if is_package else parts[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


class Fingerprinter:
    """Fingerprints functions of modules found under `roots` (the project's source roots)."""

    def __init__(self, roots: list[Path]):
        self.roots = [Path(r) for r in roots]
        self._modules: dict[str, ModuleInfo | None] = {}

    def find(self, module: str) -> ModuleInfo | None:
        if module in self._modules:
            return self._modules[module]
        info = None
        rel = Path(*module.split(".")) if module else None
        for root in self.roots if rel else []:
            for path, pkg in ((root / rel / "__init__.py", True), (root / rel.with_suffix(".py"), False)):
                if path.is_file():
                    info = self._parse(module, path, pkg)
                    break
            if info:
                break
        self._modules[module] = info
        return info

    def _parse(self, module: str, path: Path, is_package: bool) -> ModuleInfo:
        try:
            tree = ast.parse(path.read_bytes(), filename=str(path))
        except (SyntaxError, ValueError) as exc:
            line = getattr(exc, "lineno", "?")
            raise PipelineError(f"cannot parse {path}:{line}: {getattr(exc, 'msg', exc)}") from None
        _strip_docstrings(tree)
        info = ModuleInfo(module, path, is_package, tree=tree)
        preamble = hashlib.sha256()
        for stmt in tree.body:
            inner = _inner_statements(stmt) if isinstance(stmt, _COMPOUND) else []
            for s in [stmt, *inner]:
                if isinstance(s, (ast.Import, ast.ImportFrom)):
                    self._record_import(info, info.imports, s)
            if isinstance(stmt, (ast.Import, ast.ImportFrom)):
                continue
            # names bound inside a compound statement (try/except fallbacks, `if` blocks)
            # depend on the whole statement
            names = set(_bound_names(stmt))
            for s in inner:
                names.update(_bound_names(s))
                if isinstance(s, (ast.Import, ast.ImportFrom)):
                    names.update(a.asname or a.name.split(".")[0] for a in s.names if a.name != "*")
            if not names:
                preamble.update(_digest(stmt).encode())
                continue
            uses = _Uses()
            uses.visit(stmt)
            local: dict[str, Import] = {}
            for imp in uses.imports:
                self._record_import(info, local, imp)
            own = _digest(stmt)
            for name in names:
                prev = info.symbols.get(name, "")  # a name bound twice keeps every binding
                info.symbols[name] = hashlib.sha256((prev + own).encode()).hexdigest()
                info.uses.setdefault(name, set()).update(c for c in uses.chains if c != (name,))
                info.local_imports.setdefault(name, {}).update(local)
        info.preamble = preamble.hexdigest()
        return info

    def _record_import(self, info: ModuleInfo, into: dict[str, Import], stmt: ast.stmt) -> None:
        if isinstance(stmt, ast.Import):
            for a in stmt.names:
                if a.asname:
                    into[a.asname] = (a.name, None)
                else:  # `import a.b` binds `a`; a.b.x is resolved through the chain
                    top = a.name.split(".")[0]
                    into[top] = (top, None)
            return
        mod = stmt.module or ""
        if stmt.level:
            mod = _resolve_relative(info.name, info.is_package, stmt.level, stmt.module)
        for a in stmt.names:
            if a.name == "*":
                info.star.append(mod)
            else:
                into[a.asname or a.name] = (mod, a.name)

    def _closure(self, module: str, symbol: str | None, seen: set[tuple[str, str | None]]) -> None:
        if (module, symbol) in seen or (module, None) in seen:
            return
        info = self.find(module)
        if info is None:
            return  # not project code: third-party or standard library
        if symbol is not None and symbol not in info.symbols:
            if symbol in info.imports:  # re-exported name
                self._follow(info.imports[symbol], (), seen)
            elif self.find(f"{module}.{symbol}") is not None:  # `from pkg import submodule`
                self._closure(f"{module}.{symbol}", None, seen)
            else:
                for star in info.star:
                    self._closure(star, symbol, seen)
            return
        seen.add((module, symbol))
        for sym in [symbol] if symbol is not None else list(info.symbols):
            local = info.local_imports.get(sym, {})
            for base, *attrs in info.uses.get(sym, ()):
                # a name may be both bound and imported (try/except fallbacks): follow both
                if base in local:
                    self._follow(local[base], tuple(attrs), seen)
                if base in info.symbols:
                    self._closure(module, base, seen)
                if base in info.imports:
                    self._follow(info.imports[base], tuple(attrs), seen)
                if not (base in local or base in info.symbols or base in info.imports):
                    for star in info.star:
                        self._closure(star, base, seen)
        if symbol is None:  # a whole module: every import counts
            for imp in info.imports.values():
                self._follow(imp, (), seen)
            for star in info.star:
                self._closure(star, None, seen)

    def _follow(self, imp: Import, attrs: tuple[str, ...], seen) -> None:
        mod, sym = imp
        if sym is not None:
            if self.find(f"{mod}.{sym}") is None:
                self._closure(mod, sym, seen)
                return
            mod = f"{mod}.{sym}"  # `from pkg import module`
        for i, a in enumerate(attrs):  # walk `pkg.sub.deep.f` down to the symbol
            if self.find(f"{mod}.{a}") is not None:
                mod = f"{mod}.{a}"
                continue
            self._closure(mod, a, seen)
            return
        self._closure(mod, None, seen)  # the module used as a value: all of it

    def closure(self, ref: str) -> list[tuple[str, str | None]]:
        module, _, func = ref.partition(":")
        info = self.find(module)
        if info is None:
            raise PipelineError(f"cannot find module '{module}' of node function '{ref}'")
        if func not in info.symbols and func not in info.imports:
            raise PipelineError(f"module '{module}' ({info.path}) defines no '{func}'")
        seen: set[tuple[str, str | None]] = set()
        self._closure(module, func, seen)
        return sorted(seen, key=lambda t: (t[0], t[1] or ""))

    def fingerprint(self, ref: str) -> str:
        h = hashlib.sha256()
        closure = self.closure(ref)
        for module, symbol in closure:
            info = self._modules[module]
            own = info.module_digest if symbol is None else info.symbols[symbol]
            h.update(f"{module}:{symbol or '*'}:{own}\n".encode())
        for module in sorted({m for m, _ in closure}):  # module-level statements binding nothing
            h.update(f"{module}:<preamble>:{self._modules[module].preamble}\n".encode())
        return h.hexdigest()[:16]

    def files(self, ref: str) -> list[str]:
        """Source files a node's code depends on (for dvc.yaml deps)."""
        paths = {self._modules[m].path for m, _ in self.closure(ref)}
        return sorted(os.fspath(p) for p in paths)
