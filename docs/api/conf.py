"""Sphinx configuration of magcal's API reference, built from the docstrings (``python -m sphinx -n -W``)."""

import magcal

project = "magcal"
author = "the magcal developers"
copyright = "the magcal developers, BSD-3-Clause"
release = magcal.__version__

extensions = ["sphinx.ext.autodoc", "sphinx.ext.autosummary", "sphinx.ext.napoleon"]
autosummary_generate = True
templates_path = ["_templates"]
# each module page documents what the module defines (its private helpers too: docstrings refer to them), not what
# it re-exports, so a name is documented once, where it is defined
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_typehints = "description"
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
# an "Attributes" section becomes fields of its class, not a second description of each attribute
napoleon_use_ivar = True
# the engine's docstrings say types in words ("array_like", "(N, 3) array", "float, nT"): only references that
# point at a documented object are checked, not these
napoleon_preprocess_types = False
nitpicky = True
# docstrings write an absolute value or a norm as |x| (|B|, |residual|): text, not an rST substitution
rst_prolog = "\n".join(
    f".. |{text}| replace:: \\|{text}\\|" for text in ("B", "correlation", "residual", "eigenvalue", "d/q - round(d/q)")
)
# parameter and return types are words for a reader ("(N, 3) array_like, nT", "callable, optional"), not references;
# every reference a docstring makes with a role (:func:, :meth:, :class:, :mod:, :data:, :attr:) is checked
_OUTSIDE = ("warnings", "scipy", "numpy", "pandas", "pyarrow", "dask", "argparse", "collections", "multiprocessing")
_OUTSIDE += ("concurrent", "bytes", "str", "dict", "list")
nitpick_ignore_regex = [
    ("py:class", r".*"),
    # the standard library and the scientific stack are not part of this reference (no intersphinx: CI is offline)
    (r"py:.*", rf"({'|'.join(_OUTSIDE)})(\..*)?"),
]
exclude_patterns = ["_build"]
html_theme = "alabaster"

# an unqualified :attr: in a numpydoc "Attributes" section may match several classes' attributes of that name
suppress_warnings = ["ref.python"]


#: What ``_python_object`` returns for a name Python cannot find (None is a value a name may hold).
_MISSING = object()


def _python_object(target, module, klass):
    """The object ``target`` names as Python would find it from ``module`` (and ``klass``), or ``_MISSING``."""
    import importlib

    target = target.lstrip("~.")
    starts = [target]
    if module:
        starts += [f"{module}.{klass}.{target}" if klass else None, f"{module}.{target}"]
        if "." in module:
            starts.append(f"{module.rsplit('.', 1)[0]}.{target}")
    for name in filter(None, starts):
        parts = name.split(".")
        for cut in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ImportError:
                continue
            try:
                for attr in parts[cut:]:
                    obj = _attribute(obj, attr)
            except AttributeError:
                break
            return obj
    return _MISSING


def _attribute(obj, name):
    """``getattr``, or for a class an instance attribute: a dataclass field, an annotation or ``self.name = ...``."""
    import inspect

    if hasattr(obj, name):
        return getattr(obj, name)
    if inspect.isclass(obj):
        for klass in obj.__mro__:
            if name in getattr(klass, "__annotations__", {}) or name in getattr(klass, "__slots__", ()):
                return name
            try:
                source = inspect.getsource(klass)
            except (OSError, TypeError):
                continue
            if f"self.{name} =" in source or f"self.{name}:" in source:
                return name
    raise AttributeError(name)


def _resolve_by_import(app, env, node, contnode):
    """A reference Sphinx cannot find is accepted when Python finds what it names (a re-exported name such as
    ``magcal.calibrate``, a module constant, a method reached through its class), linked to where the object is
    documented; a name that Python cannot find either stays a warning, so ``-W`` fails on it."""
    if node.get("refdomain") != "py":
        return None
    obj = _python_object(node["reftarget"], node.get("py:module"), node.get("py:class"))
    if obj is _MISSING:
        return None
    domain = env.get_domain("py")
    qualname = getattr(obj, "__qualname__", None)
    owner = getattr(obj, "__module__", None)
    if qualname and owner:
        canonical = f"{owner}.{qualname}"
        if canonical in domain.objects:
            from sphinx.util.nodes import make_refnode

            entry = domain.objects[canonical]
            return make_refnode(app.builder, node["refdoc"], entry.docname, entry.node_id, contnode, canonical)
    return contnode


def setup(app):
    app.connect("missing-reference", _resolve_by_import)
