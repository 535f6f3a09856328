"""numpydoc on every public function, class and method (issue 16, item 6).

Each checked object needs a docstring that numpydoc parses without a warning, with a one-line
summary, and

- functions and methods: a Parameters section naming exactly the signature's parameters, in
  order (not ``self``/``cls``; ``*args``/``**kwargs`` by their names, with or without the
  stars), and a Returns (or Yields) section unless the function returns None (its return
  annotation is ``None``; without an annotation, its body has no ``return value``/``yield``);
- classes: a Parameters or an Attributes section; Parameters, when given, name exactly the
  constructor's parameters.

What is checked is listed in :data:`PUBLIC`, module by module; every public method defined in
the body of a checked class is checked too (properties are attributes and are not).
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import textwrap
import warnings

import pytest
from numpydoc.docscrape import ClassDoc, FunctionDoc, ParseError

#: Everything public defined in the module itself (for modules without ``__all__``).
DEFINED_HERE = "defined here"

#: module -> which of its names are public API: ``"__all__"``, :data:`DEFINED_HERE`, or a tuple.
PUBLIC: dict[str, str | tuple[str, ...]] = {
    "geocoder": "__all__",  # register, ingest, open_scene, options, errors, Status, RegisterOptions
    "geocoder.cog": "__all__",  # to_cog
    "geocoder.mosaic": "__all__",  # mosaic() and what the package exports with it
    "geocoder.mosaic.placement": "__all__",  # scenes the reference misses, placed through their neighbours
    "geocoder.pipeline.simulate": ("simulate",),  # the entry point of `geocoder simulate`
    # geocoder.adjust exports nothing itself: its entry points are the file-level run of
    # `geocoder adjust` and the solver and sensor models a notebook calls
    "geocoder.adjust.run": ("adjust_files",),
    "geocoder.adjust.solver": "__all__",
    "geocoder.adjust.models": "__all__",
    "geocoder.accessor": "__all__",  # the two accessor classes (their methods are added below)
    "geocoder.options": DEFINED_HERE,  # set_options, get_option, get_options
    "geocoder.cluster": DEFINED_HERE,  # up, down, read_info, ClusterInfo, Stopped, ...
    "geocoder.reporting": "__all__",  # report(), require_matplotlib
    "geocoder.reporting.analysis": "__all__",  # the report's pure functions (HSI, along-track spectrum, ...)
}

#: Public names that are not callables (nothing to check), each with why.
NOT_CALLABLE = {
    "geocoder.__version__": "the version string",
}

#: Fewer checked objects than this means the walk broke (76 when written; 9 of them xfail).
FLOOR = 75

#: Objects known to fail the check, each with why (empty: every one passes); strict, so an
#: entry that starts passing fails until it is removed from here.
XFAIL: dict[str, str] = {}


# ----------------------------------------------------------------------------- the walk
def _public_names(module) -> list[str]:
    how = PUBLIC[module.__name__]
    if how == "__all__":
        return list(module.__all__)
    if how == DEFINED_HERE:
        return [name for name, obj in vars(module).items()
                if not name.startswith("_") and (inspect.isfunction(obj) or inspect.isclass(obj))
                and obj.__module__ == module.__name__]
    return list(how)


def _methods(cls) -> list[tuple[str, object]]:
    """Public functions defined in the class body (not inherited, not properties)."""
    out = []
    for name, value in vars(cls).items():
        if name.startswith("_"):
            continue
        if isinstance(value, (staticmethod, classmethod)) or inspect.isfunction(value):
            out.append((name, value))
    return out


def _walk() -> list[tuple[str, object]]:
    found: list[tuple[str, object]] = []
    seen: set[int] = set()

    def add(path, obj):
        key = id(obj.__func__ if isinstance(obj, (staticmethod, classmethod)) else obj)
        if key not in seen:
            seen.add(key)
            found.append((path, obj))

    for module_name in PUBLIC:
        module = importlib.import_module(module_name)
        for name in _public_names(module):
            path = f"{module_name}.{name}"
            obj = getattr(module, name)
            if not callable(obj):
                assert path in NOT_CALLABLE, f"{path} is public but neither callable nor listed in NOT_CALLABLE"
                continue
            add(path, obj)
            if inspect.isclass(obj):
                for method_name, method in _methods(obj):
                    add(f"{path}.{method_name}", method)
    return found


CHECKED = _walk()


# ----------------------------------------------------------------------------- the rules
def _own_doc(obj) -> str | None:
    """The object's own docstring: not inherited, not the one ``dataclass`` makes up."""
    if inspect.isclass(obj):
        doc = vars(obj).get("__doc__")
        if doc and dataclasses.is_dataclass(obj) and doc.startswith(f"{obj.__name__}("):
            return None
    else:
        doc = obj.__doc__
    return inspect.cleandoc(doc) if doc and doc.strip() else None


def _documented_names(section) -> list[str]:
    """Names of a Parameters section; ``a, b : float`` gives both, stars are dropped."""
    return [name.strip().lstrip("*") for p in section for name in p.name.split(",") if name.strip()]


def _compare(documented: list[str], expected: list[str]) -> list[str]:
    missing = [n for n in expected if n not in documented]
    extra = [n for n in documented if n not in expected]
    problems = []
    if missing:
        problems.append(f"Parameters lacks {missing}")
    if extra:
        problems.append(f"Parameters names {extra}, not in the signature")
    if not problems and documented != expected:
        problems.append(f"Parameters in another order than the signature: {documented}, expected {expected}")
    return problems


def _returns_value(fn) -> bool:
    annotation = inspect.signature(fn).return_annotation
    if annotation is not inspect.Signature.empty:
        return annotation not in (None, "None", type(None))
    tree = ast.parse(textwrap.dedent(inspect.getsource(fn))).body[0]
    for node in ast.walk(tree):
        gives = isinstance(node, (ast.Yield, ast.YieldFrom)) or (isinstance(node, ast.Return) and node.value is not None)
        if gives and _owner(tree, node) is tree:
            return True
    return False


def _owner(tree, target):
    """The innermost function (or lambda) of ``tree`` that contains ``target``."""
    owner = tree
    for node in ast.walk(tree):
        inner = node is not tree and isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
        if inner and any(child is target for child in ast.walk(node)):
            owner = node
    return owner


def _parse(cls_or_fn, doc: str, problems: list[str]):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if inspect.isclass(cls_or_fn):
            parsed = ClassDoc(cls_or_fn, doc=doc, config={"show_class_members": False})
        else:
            parsed = FunctionDoc(cls_or_fn, doc=doc)
    problems += [f"numpydoc: {w.message}" for w in caught]
    summary = parsed["Summary"]
    if not summary:
        problems.append("no summary line")
    elif len(summary) > 1:
        problems.append("the summary takes more than one line")
    return parsed


def docstring_problems(obj, *, method: bool = False) -> list[str]:
    """What the numpydoc docstring of ``obj`` lacks (empty: nothing).

    Parameters
    ----------
    obj : callable
        A function, class, or (with ``method``) a function, staticmethod or classmethod taken
        from a class body.
    method : bool
        ``obj`` comes from a class body: a plain function's first parameter is ``self`` and a
        classmethod's is ``cls``; neither is documented.

    Returns
    -------
    list of str
        One entry per problem.
    """
    skip_first = method and not isinstance(obj, staticmethod)
    fn = obj.__func__ if isinstance(obj, (staticmethod, classmethod)) else obj
    doc = _own_doc(fn)
    if doc is None:
        return ["no docstring"]
    problems: list[str] = []
    try:
        parsed = _parse(fn, doc, problems)
    except (ParseError, ValueError) as exc:  # numpydoc's errors on malformed sections
        return [f"numpydoc cannot parse it: {exc}"]
    if inspect.isclass(fn):
        if not parsed["Parameters"] and not parsed["Attributes"]:
            problems.append("neither a Parameters nor an Attributes section")
        if parsed["Parameters"]:
            try:
                expected = list(inspect.signature(fn).parameters)
            except ValueError:
                problems.append("a Parameters section, but the constructor has no signature to check it against")
            else:
                problems += _compare(_documented_names(parsed["Parameters"]), expected)
        return problems
    expected = list(inspect.signature(fn).parameters)
    if skip_first:
        expected = expected[1:]
    problems += _compare(_documented_names(parsed["Parameters"]), expected)
    if _returns_value(fn) and not (parsed["Returns"] or parsed["Yields"]):
        problems.append("no Returns (or Yields) section")
    return problems


# ----------------------------------------------------------------------------- the tests
def _is_method(path: str) -> bool:
    owner = path.rsplit(".", 1)[0]
    return any(p == owner and inspect.isclass(o) for p, o in CHECKED)


@pytest.mark.parametrize(
    "path,obj",
    [pytest.param(path, obj, id=path,
                  marks=[pytest.mark.xfail(strict=True, reason=XFAIL[path])] if path in XFAIL else [])
     for path, obj in CHECKED],
)
def test_numpydoc(path, obj):
    problems = docstring_problems(obj, method=_is_method(path))
    assert not problems, f"{path}: " + "; ".join(problems)


def test_the_walk_checks_the_public_api():
    paths = [p for p, _ in CHECKED]
    assert len(paths) >= FLOOR, f"only {len(paths)} objects checked: {paths}"
    for expected in ("geocoder.register", "geocoder.ingest", "geocoder.open_scene", "geocoder.set_options",
                     "geocoder.cog.to_cog", "geocoder.mosaic.mosaic", "geocoder.pipeline.simulate.simulate",
                     "geocoder.adjust.run.adjust_files", "geocoder.adjust.solver.adjust",
                     "geocoder.accessor.GeocoderArrayAccessor.register", "geocoder.accessor.GeocoderDatasetAccessor.summary",
                     "geocoder.cluster.up", "geocoder.cluster.down"):
        assert expected in paths
    stale = sorted(set(XFAIL) - set(paths))
    assert not stale, f"XFAIL names objects that are not checked: {stale}"


def _good(a, b=1, *args, c, **kwargs):
    """Add.

    Parameters
    ----------
    a, b : int
        Terms.
    *args
        More terms.
    c : int
        Another.
    **kwargs
        Ignored.

    Returns
    -------
    int
        The sum.
    """
    return a + b + c + sum(args)


def _no_returns(a: int) -> int:
    """Add one.

    Parameters
    ----------
    a : int
        A term.
    """
    return a + 1


def _wrong_names(a, c):
    """Nothing.

    Parameters
    ----------
    a : int
        A term.
    b : int
        Not a parameter.
    """


def _inner_return_only(a):
    """Nothing returned: only the inner function returns.

    Parameters
    ----------
    a : int
        A term.
    """

    def inner():
        return a

    inner()


class _Undocumented:
    """A class without sections."""

    def method(self, x):
        """Take x.

        Parameters
        ----------
        x : int
            Anything.
        """


def test_the_rules_flag_what_they_should():
    assert docstring_problems(_good) == []
    assert docstring_problems(_no_returns) == ["no Returns (or Yields) section"]
    assert docstring_problems(_wrong_names) == ["Parameters lacks ['c']", "Parameters names ['b'], not in the signature"]
    assert docstring_problems(_inner_return_only) == []
    assert docstring_problems(lambda: None) == ["no docstring"]
    assert docstring_problems(_Undocumented) == ["neither a Parameters nor an Attributes section"]
    assert docstring_problems(vars(_Undocumented)["method"], method=True) == []
