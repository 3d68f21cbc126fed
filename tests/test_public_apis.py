"""The project touches no private attribute of another library (issue 22): every ``x._name`` in
its Python sources (``daemon``, ``protocols``, ``replay``, ``bench``, ``tests``) is one of its own.

Read with :mod:`ast`, an access ``x._name`` (one leading underscore) is refused when

* ``x`` is a third-party module, class or object (a name bound by importing one, or assigned from a
  call of one: ``client = paho.Client(...)``; ``client._sock``);
* ``_name`` is a private name of the third-party modules and classes the project uses (their
  ``dir()``, and the ``self._name`` their classes' sources assign): ``message._topic``;
* ``_name`` is defined nowhere in the project (no ``def``, class, assignment to ``self._name``, field,
  ``__slots__`` entry or module name of that name), unless it is one of the few documented names
  that begin with an underscore (``os._exit``, namedtuple's ``_replace``);

and a class of the project that derives from a third-party class may not define or use a private
name of its base (overriding ``aiomqtt.Client._on_socket_open``). ``self._name`` in the project's own
classes is always the project's. A patch release of a dependency may change or remove anything
private, silently.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import sys
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from tests.helpers import REPO

PACKAGES = ("daemon", "protocols", "replay", "bench", "tests")
DOCUMENTED = frozenset({"_exit", "_getframe", "_replace", "_asdict", "_fields", "_make", "_field_defaults"})
"""Names beginning with an underscore that their libraries document (``os._exit``,
``sys._getframe``, :func:`collections.namedtuple`'s methods)."""


def private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__") and name != "_"


def third_party(dotted: str) -> bool:
    root = dotted.split(".")[0]
    return root not in PACKAGES and root not in sys.stdlib_module_names


def sources(root: Path = REPO) -> Iterator[Path]:
    for package in PACKAGES:
        yield from sorted((root / package).rglob("*.py"))


@dataclass
class Module:
    """One source file: what its imports bind, what it defines, and its private accesses."""

    path: str
    tree: ast.Module
    bound: dict[str, str] = field(default_factory=dict)  # local name -> the dotted name it stands for

    @classmethod
    def parse(cls, text: str, path: str) -> Module:
        module = cls(path, ast.parse(text))
        for node in ast.walk(module.tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.asname is not None:
                        module.bound[alias.asname] = alias.name
                    else:
                        module.bound[alias.name.split(".")[0]] = alias.name.split(".")[0]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module is not None:
                for alias in node.names:
                    module.bound[alias.asname or alias.name] = f"{node.module}.{alias.name}"
        # names assigned from a third-party call or attribute: (module-wide; a few passes for chains)
        for _ in range(3):
            for node in ast.walk(module.tree):
                if isinstance(node, ast.Assign | ast.AnnAssign) and node.value is not None:
                    origin = module.origin(node.value)
                    if origin is None or not third_party(origin):
                        continue
                    targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                    for target in targets:
                        name = module.target_name(target)
                        if name is not None and name not in module.bound:
                            module.bound[name] = origin
        return module

    @staticmethod
    def target_name(node: ast.expr) -> str | None:
        """``x`` or ``self.x`` (as ``self.x``)."""
        if isinstance(node, ast.Name):
            return node.id
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            return f"{node.value.id}.{node.attr}"
        return None

    def origin(self, node: ast.expr) -> str | None:
        """The dotted name ``node`` stands for, if it is rooted in an import or a bound name."""
        if isinstance(node, ast.Call):
            return self.origin(node.func)
        if isinstance(node, ast.Name):
            return self.bound.get(node.id)
        if isinstance(node, ast.Attribute):
            if isinstance(node.value, ast.Name) and f"{node.value.id}.{node.attr}" in self.bound:
                return self.bound[f"{node.value.id}.{node.attr}"]
            base = self.origin(node.value)
            return None if base is None else f"{base}.{node.attr}"
        return None

    def defined(self) -> set[str]:
        """The private names this file defines."""
        out: set[str] = set()
        for node in ast.walk(self.tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                out.add(node.name)
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                out.add(node.id)
            elif (
                isinstance(node, ast.Attribute)
                and isinstance(node.ctx, ast.Store)
                and isinstance(node.value, ast.Name)
                and node.value.id in ("self", "cls")
            ):
                out.add(node.attr)
            elif isinstance(node, ast.alias):
                out.add(node.asname or node.name.split(".")[0])
            elif (
                isinstance(node, ast.Assign)
                and any(isinstance(t, ast.Name) and t.id == "__slots__" for t in node.targets)
                and isinstance(node.value, ast.Tuple | ast.List)
            ):
                out.update(str(e.value) for e in node.value.elts if isinstance(e, ast.Constant))
        return {name for name in out if private(name)}

    def accesses(self) -> Iterator[tuple[ast.AST, ast.expr, str]]:
        """Every private attribute access: (node, the object, the name); ``getattr(x, "_name")``
        and its kin too."""
        for node in ast.walk(self.tree):
            if isinstance(node, ast.Attribute) and private(node.attr):
                yield node, node.value, node.attr
            elif (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in ("getattr", "setattr", "hasattr", "delattr")
                and len(node.args) >= 2
                and isinstance(node.args[1], ast.Constant)
                and isinstance(node.args[1].value, str)
                and private(node.args[1].value)
            ):
                yield node, node.args[0], node.args[1].value


@cache
def resolve(dotted: str) -> Any:
    """The object a dotted name stands for (the longest importable module, then attributes);
    None if it cannot be found (a name made at run time, an optional library)."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:cut]))
        except Exception:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name, None)
            if obj is None:
                return None
        return obj
    return None


@cache
def assigned_privates(path: str) -> frozenset[str]:
    """The ``self._name`` a third-party source file assigns (instance attributes dir() cannot see)."""
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return frozenset()
    return frozenset(
        node.attr
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute)
        and isinstance(node.value, ast.Name)
        and node.value.id == "self"
        and private(node.attr)
    )


def privates_of(obj: Any) -> set[str]:
    """The private names of a third-party module (its own and its classes') or class (its MRO's,
    with the instance attributes their sources assign)."""
    out = {name for name in dir(obj) if private(name)}
    if inspect.ismodule(obj):
        for value in vars(obj).values():
            if inspect.isclass(value):
                out |= {name for name in dir(value) if private(name)}
    elif inspect.isclass(obj):
        for base in obj.__mro__:
            module = sys.modules.get(base.__module__)
            path = getattr(module, "__file__", None)
            if path is not None and third_party(base.__module__):
                out |= assigned_privates(path)
    return out


def third_party_privates(modules: list[Module]) -> set[str]:
    out: set[str] = set()
    for module in modules:
        for origin in set(module.bound.values()):
            if third_party(origin):
                obj = resolve(origin)
                if inspect.ismodule(obj) or inspect.isclass(obj):
                    out |= privates_of(obj)
                elif obj is not None:
                    out |= privates_of(type(obj))
    return out


def findings(modules: list[Module], own: set[str], foreign: set[str]) -> list[str]:
    out = []
    for module in modules:
        subclassing: dict[ast.AST, set[str]] = {}  # in a class of a third-party base: its privates
        for node in ast.walk(module.tree):
            if not isinstance(node, ast.ClassDef):
                continue
            names: set[str] = set()
            for base in node.bases:
                origin = module.origin(base)
                if origin is not None and third_party(origin) and inspect.isclass(resolve(origin)):
                    names |= privates_of(resolve(origin))
                    for item in node.body:
                        if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef) and item.name in names:
                            out.append(f"{module.path}:{item.lineno}: overrides {origin}'s {item.name}")
            for inner in ast.walk(node) if names else ():
                subclassing[inner] = names
        for node, value, name in module.accesses():
            where = f"{module.path}:{getattr(node, 'lineno', 0)}: {ast.unparse(node)}"
            if isinstance(value, ast.Name) and value.id in ("self", "cls"):
                if name in subclassing.get(node, set()):
                    out.append(f"{where} (a private name of a third-party base class)")
                continue
            origin = module.origin(value)
            if origin is not None and third_party(origin):
                out.append(f"{where} (private, of {origin})")
            elif name in foreign:
                out.append(f"{where} (a private name of a third-party library)")
            elif name not in own and name not in DOCUMENTED:
                out.append(f"{where} (private, and not the project's)")
    return out


def check(modules: list[Module]) -> list[str]:
    """What :func:`findings` refuses in ``modules``, in order of file and line."""
    own = set().union(*(m.defined() for m in modules))
    found = findings(modules, own, third_party_privates(modules))
    return sorted(set(found), key=lambda f: (f.split(":")[0], int(f.split(":")[1]), f))


@cache
def repository() -> tuple[Module, ...]:
    return tuple(Module.parse(p.read_text(encoding="utf-8"), str(p.relative_to(REPO))) for p in sources())


def test_no_private_attribute_of_another_library_is_touched() -> None:
    assert check(list(repository())) == []


OLD_MQTT = textwrap.dedent(
    """
    import aiomqtt

    class _Client(aiomqtt.Client):
        def __init__(self, *args, deliver, **kwargs):
            super().__init__(*args, **kwargs)
            self._read = self._client._sock_recv
            self._client._sock_recv = self._read

            def handle(message):
                deliver(message._topic.decode(), message.payload)

            self._client._handle_on_message = handle

        def _on_socket_open(self, client, userdata, sock):
            self._loop.call_soon_threadsafe(self._loop.add_reader, sock.fileno(), client.loop_read)
    """
)
"""The patches the MQTT transport once made to aiomqtt and paho (before issue 22), in short."""


def test_the_check_finds_the_patches_that_were() -> None:
    found = check([*repository(), Module.parse(OLD_MQTT, "old_mqtt.py")])
    old = [f for f in found if f.startswith("old_mqtt.py:")]
    for expected in (
        "self._client._sock_recv",
        "message._topic",
        "self._client._handle_on_message",
        "overrides aiomqtt.Client's _on_socket_open",
        "self._loop",
        "self._client ",
    ):
        assert any(expected in f for f in old), (expected, old)
    assert not any("self._read" in f for f in old)  # the subclass's own attribute
    assert len(found) == len(old)


def test_the_check_follows_objects_and_getattr() -> None:
    """Through a name given a third-party object, and through ``getattr``: a private name of the
    project's own is refused there too."""
    snippet = textwrap.dedent(
        """
        import paho.mqtt.client as paho

        class Mine:
            def __init__(self):
                self._sock = None
                self.mqtt = paho.Client()

            def read(self):
                return self.mqtt._sock, getattr(self.mqtt, "_out_packet"), self._sock
        """
    )
    found = check([*repository(), Module.parse(snippet, "snippet.py")])
    assert {f.split(": ", 1)[1] for f in found} == {
        "self.mqtt._sock (private, of paho.mqtt.client.Client)",
        "getattr(self.mqtt, '_out_packet') (private, of paho.mqtt.client.Client)",
    }
