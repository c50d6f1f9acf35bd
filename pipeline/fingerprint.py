"""Code fingerprints from source ASTs, without importing anything.

A node's fingerprint covers the normalised AST (no comments, docstrings or layout) of
its function and, transitively, of every project-level symbol it uses: functions,
classes and constants of its own module, and symbols imported from other modules of
the project. Third-party and standard-library names are not followed.
"""
from __future__ import annotations

import ast
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import PipelineError


@dataclass
class ModuleInfo:
    name: str
    path: Path
    is_package: bool
    symbols: dict[str, str] = field(default_factory=dict)       # symbol -> own AST digest
    uses: dict[str, set[str]] = field(default_factory=dict)     # symbol -> names it uses
    attr_uses: dict[str, set[tuple[str, str]]] = field(default_factory=dict)
    imports: dict[str, tuple[str, str | None]] = field(default_factory=dict)  # alias -> (module, symbol)
    module_digest: str = ""


def _strip_docstrings(tree: ast.AST) -> None:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]


def _digest(node: ast.AST) -> str:
    return hashlib.sha256(ast.dump(node, include_attributes=False).encode()).hexdigest()


def _bound_names(stmt: ast.stmt) -> list[str]:
    if isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [stmt.name]
    targets: list[ast.expr] = []
    if isinstance(stmt, ast.Assign):
        targets = stmt.targets
    elif isinstance(stmt, (ast.AnnAssign, ast.AugAssign)):
        targets = [stmt.target]
    names = []
    for t in targets:
        names += [n.id for n in ast.walk(t) if isinstance(n, ast.Name)]
    return names


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
        rel = Path(*module.split("."))
        for root in self.roots:
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
            tree = ast.parse(path.read_text(), filename=str(path))
        except SyntaxError as exc:
            raise PipelineError(f"syntax error in {path}:{exc.lineno}: {exc.msg}") from None
        _strip_docstrings(tree)
        info = ModuleInfo(module, path, is_package, module_digest=_digest(tree))
        for stmt in tree.body:
            if isinstance(stmt, (ast.Import, ast.ImportFrom)):
                self._record_import(info, stmt)
                continue
            for name in _bound_names(stmt):
                # a name bound twice (e.g. try/except fallbacks) keeps every binding
                prev = info.symbols.get(name, "")
                info.symbols[name] = hashlib.sha256((prev + _digest(stmt)).encode()).hexdigest()
                names, attrs = set(), set()
                for n in ast.walk(stmt):
                    if isinstance(n, ast.Name):
                        names.add(n.id)
                    elif isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name):
                        attrs.add((n.value.id, n.attr))
                info.uses.setdefault(name, set()).update(names - {name})
                info.attr_uses.setdefault(name, set()).update(attrs)
        return info

    def _record_import(self, info: ModuleInfo, stmt: ast.stmt) -> None:
        if isinstance(stmt, ast.Import):
            for a in stmt.names:
                if a.asname:
                    info.imports[a.asname] = (a.name, None)
                else:  # `import a.b` binds `a`
                    top = a.name.split(".")[0]
                    info.imports[top] = (top, None)
            return
        assert isinstance(stmt, ast.ImportFrom)
        mod = stmt.module or ""
        if stmt.level:
            mod = _resolve_relative(info.name, info.is_package, stmt.level, stmt.module)
        for a in stmt.names:
            if a.name != "*":
                info.imports[a.asname or a.name] = (mod, a.name)

    def _closure(self, module: str, symbol: str | None, seen: set[tuple[str, str | None]]) -> None:
        if (module, symbol) in seen:
            return
        info = self.find(module)
        if info is None:
            return  # not project code: third-party or standard library
        if symbol is not None and symbol not in info.symbols:
            if symbol in info.imports:  # re-exported name
                self._follow_import(info, symbol, None, seen)
                return
            sub = f"{module}.{symbol}"
            if self.find(sub) is not None:  # `from pkg import submodule`
                self._closure(sub, None, seen)
            return
        seen.add((module, symbol))
        symbols = [symbol] if symbol is not None else list(info.symbols)
        for sym in symbols:
            for name in info.uses.get(sym, ()):
                if name in info.symbols:
                    self._closure(module, name, seen)
                elif name in info.imports:
                    attrs = {a for base, a in info.attr_uses.get(sym, ()) if base == name}
                    self._follow_import(info, name, attrs, seen)
        if symbol is None:  # whole module: its imports count too
            for alias in info.imports:
                self._follow_import(info, alias, None, seen)

    def _follow_import(self, info: ModuleInfo, alias: str, attrs: set[str] | None,
                       seen: set[tuple[str, str | None]]) -> None:
        mod, sym = info.imports[alias]
        if sym is not None and self.find(f"{mod}.{sym}") is not None:  # `from pkg import module`
            mod, sym = f"{mod}.{sym}", None
        if sym is None:  # a module object: follow the attributes used on it
            if attrs:
                for a in attrs:
                    self._closure(mod, a, seen)
            else:
                self._closure(mod, None, seen)
        else:
            self._closure(mod, sym, seen)

    def closure(self, ref: str) -> list[tuple[str, str | None]]:
        module, _, func = ref.partition(":")
        info = self.find(module)
        if info is None:
            raise PipelineError(f"cannot find module '{module}' of node function '{ref}'")
        if func not in info.symbols and func not in info.imports:
            raise PipelineError(f"module '{module}' ({info.path}) defines no '{func}'")
        seen: set[tuple[str, str | None]] = set()
        self._closure(module, func, seen)
        if not seen:  # the function is itself an import into that module
            self._follow_import(info, func, None, seen)
        return sorted(seen, key=lambda t: (t[0], t[1] or ""))

    def fingerprint(self, ref: str) -> str:
        h = hashlib.sha256()
        for module, symbol in self.closure(ref):
            info = self._modules[module]
            own = info.module_digest if symbol is None else info.symbols[symbol]
            h.update(f"{module}:{symbol or '*'}:{own}\n".encode())
        return h.hexdigest()[:16]

    def files(self, ref: str) -> list[str]:
        """Source files a node's code depends on (for dvc.yaml deps)."""
        paths = {self._modules[m].path for m, _ in self.closure(ref)}
        return sorted(os.fspath(p) for p in paths)
