"""This site's autodoc fixes (a local Sphinx extension, loaded by ``docs/conf.py``).

Constants: autodoc reads a constant's ``#:`` doc comment only in the module it is documented from, so a
constant re-exported by a package (``torchrl_dalir.reranking.CANDIDATE_SCORES``, defined in
``torchrl_dalir.reranking.actor``) would show the docstring of its type (``tuple``'s). This follows the
package's ``from ... import`` to the defining module and uses that comment; a constant listed in its
module's ``__all__`` without one is a warning (so ``-W`` fails the build).

Classes show their ``__init__`` arguments: TensorDict modules and TorchRL losses inherit a
``__new__(*args, **kwargs)`` that autodoc would show instead; a ``typing.Protocol`` shows none.
"""

from __future__ import annotations

import ast
import importlib
import inspect

from sphinx.pycode import ModuleAnalyzer
from sphinx.util import logging
from sphinx.util.inspect import signature, stringify_signature

logger = logging.getLogger(__name__)


def _imported_from(module_name: str, name: str) -> tuple[str, str] | None:
    """Where ``module_name`` imports ``name`` from: ``(module, name there)``, or None."""
    try:
        source = ModuleAnalyzer.for_module(module_name).code
    except Exception:  # no source (a compiled module)
        return None
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                if (alias.asname or alias.name) == name:
                    return node.module, alias.name
    return None


def data_doc(module_name: str, name: str, depth: int = 5) -> list[str] | None:
    """The ``#:`` doc comment (lines) of ``module_name.name``, followed through re-exports; None if none."""
    for _ in range(depth):
        try:
            docs = ModuleAnalyzer.for_module(module_name).find_attr_docs()
        except Exception:
            return None
        if ("", name) in docs:
            return [line for line in docs[("", name)] if line is not None]
        origin = _imported_from(module_name, name)
        if origin is None:
            return None
        module_name, name = origin
    return None


def _process_docstring(app, what, name, obj, options, lines):
    if what != "data":
        return
    module_name, _, attr = name.rpartition(".")
    doc = data_doc(module_name, attr)
    if doc is not None:
        lines[:] = doc
        return
    if type(obj).__doc__ and inspect.cleandoc(type(obj).__doc__).splitlines()[:1] == lines[:1]:
        lines[:] = []  # the type's docstring says nothing about this constant
    try:
        public = attr in getattr(importlib.import_module(module_name), "__all__", ())
    except ImportError:
        public = False
    if public and not lines:
        logger.warning("%s is public (in __all__) but has no '#:' doc comment where it is defined", name)


def _process_signature(app, what, name, obj, options, args, return_annotation):
    if what not in ("class", "exception") or args != "(*args, **kwargs)":
        return None
    if getattr(obj, "_is_protocol", False):
        return "", return_annotation
    if "__init__" not in {attr for klass in inspect.getmro(obj)[:-1] for attr in vars(klass)}:
        return None
    init = signature(obj.__init__, bound_method=True, type_aliases=app.config.autodoc_type_aliases)
    short = app.config.autodoc_typehints_format == "short"
    return stringify_signature(init, show_return_annotation=False, unqualified_typehints=short), return_annotation


def setup(app):
    app.connect("autodoc-process-docstring", _process_docstring)
    app.connect("autodoc-process-signature", _process_signature)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
