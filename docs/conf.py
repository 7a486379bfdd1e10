"""Sphinx configuration of the densityloop documentation (``make docs``).

The build runs with warnings as errors and in nitpicky mode (every cross-reference must
resolve). The hooks here let the docstrings stay as they are, plain text written to be
read in a terminal as much as in a browser:

* :func:`plain_text_docstring` escapes ``|`` (norms such as ``|v_k|``, which
  reStructuredText reads as substitutions) and turns a paragraph that ends with ``:``
  and is followed by an indented block (formulas, the docstrings' usual layout) into a
  literal block;
* :func:`joined_names` joins an ``Args:`` entry that names several parameters over two
  lines, and :func:`free_text_returns` keeps napoleon from reading the words before the
  first colon of a ``Returns:`` section or of an attribute's docstring as a type when
  they are a sentence;
* :func:`skip_tuple_fields` leaves a named tuple's fields to its ``Attributes:``;
* :func:`resolve_short_name` resolves a reference that names an object by a shorter
  path than its full one (``Grid.l2``, ``ConfigError`` from another module, a method
  inherited from a base class, a name a package re-exports) when exactly one documented
  object fits.

The directives ``automodules`` and ``modules-table`` build the API reference from the
package tree, so a new module joins it without an edit. The directive ``config-options``
and the role ``options`` list a config group's options from ``conf/<group>/``, so a new
option (a law, a plant) joins the pages that list them without an edit.

References to other projects (numpy, scipy, the standard library, Hydra, omegaconf,
xarray, foxglove) are left unlinked: the build reaches no network, so there is no
inventory to link them to (``nitpick_ignore_regex``). Private helpers (``_name``) are
not part of the reference either. ``nitpick_ignore`` lists the few attributes without a
docstring of their own that docstrings refer to.
"""

from __future__ import annotations

import importlib
import pkgutil
import re
import sys
from pathlib import Path
from typing import Any, ClassVar

import yaml
from docutils import nodes
from docutils.parsers.rst import directives
from sphinx import addnodes
from sphinx.ext.napoleon.docstring import GoogleDocstring
from sphinx.util.docutils import SphinxDirective
from sphinx.util.parsing import nested_parse_to_nodes

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

project = "densityloop"
author = "densityloop contributors"
project_copyright = "densityloop contributors"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "*.in.md", "**/*.in.md", "studies/data"]

myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

autodoc_default_options = {
    "members": True,
    "ignore-module-all": True,  # every public name, also those a module leaves out of __all__
    "show-inheritance": True,
    "special-members": "__call__",
}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
napoleon_google_docstring = True
napoleon_numpy_docstring = False

nitpicky = True
_EXTERNAL = (
    r"(numpy|np|scipy|sp|omegaconf|hydra|xarray|xr|yaml|foxglove|mcap|mcap_protobuf|google"
    r"|numba|matplotlib|plt|threadpoolctl|ot|tqdm|websockets|submitit|joblib|filterpy"
    # the standard library
    r"|Path|pathlib|os|sys|io|collections|typing|types|abc|datetime|time|socket|threading"
    r"|subprocess|signal|json|argparse|logging|contextlib|enum|functools|itertools"
    r"|dataclasses|tempfile|shutil|re|math|concurrent|multiprocessing|asyncio|queue"
    r"|selectors|http|urllib|errno|resource|platform|inspect|importlib|warnings|numbers"
    r"|random|struct|hashlib|zlib|csv|textwrap|string|copy|weakref|uuid|base64)(\..*)?"
)
nitpick_ignore_regex = [
    (r"py:(class|exc|func|meth|data|attr|obj)", _EXTERNAL),
    (r"py:(class|func|meth|data|attr|obj)", r"(.*\.)?_[A-Za-z]\w*"),  # private helpers
]
nitpick_ignore = [
    # attributes set in __init__ without a docstring of their own, in files others are
    # editing: remove an entry once the attribute has its docstring
    ("py:attr", "port"),  # harness/observers/live.py, LiveServer.port
    ("py:attr", "gradient"),  # harness/estimators/distributed/filters.py, RobotFilters.gradient
]

highlight_language = "none"  # docstrings' literal blocks are formulas, not code
html_theme = "furo"
html_title = "densityloop"
html_static_path: list[str] = []

# -- plain-text docstrings -------------------------------------------------------------

_INLINE = re.compile(r"(``.+?``|:[a-z:]+:`[^`]*`|`[^`]*`)")
"""Inline literals, roles and interpreted text: left as they are."""


def _escape_bars(line: str) -> str:
    """``|`` outside inline literals and roles, escaped."""
    parts = _INLINE.split(line)
    return "".join(p if i % 2 else p.replace("|", r"\|") for i, p in enumerate(parts))


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def plain_text_docstring(
    app: Any, what: str, name: str, obj: Any, options: Any, lines: list[str]
) -> None:
    """Make a plain-text docstring valid reStructuredText, in place (after napoleon).

    A paragraph that ends with ``:`` and is followed, after a blank line, by a block
    indented deeper becomes a literal block (``::``); ``|`` outside literals is escaped.
    """
    literal_indent: int | None = None
    for i, line in enumerate(lines):
        if literal_indent is not None:
            if not line.strip() or _indent(line) > literal_indent:
                continue
            literal_indent = None
        stripped = line.rstrip()
        if stripped.endswith("::"):
            literal_indent = _indent(line)
        elif stripped.endswith(":") and not stripped.lstrip().startswith(":"):
            nxt = next((j for j in range(i + 1, len(lines)) if lines[j].strip()), None)
            if nxt is not None and nxt > i + 1 and _indent(lines[nxt]) > _indent(line):
                stripped += ":"
                literal_indent = _indent(line)
        lines[i] = _escape_bars(stripped)


_SECTION = re.compile(r"^(\s*)(Args|Arguments|Parameters|Keyword Args|Attributes):\s*$")


def joined_names(app: Any, what: str, name: str, obj: Any, options: Any, lines: list[str]) -> None:
    """Join an ``Args:`` entry that lists several names over two lines (``grid, model,
    ...,`` then ``seed, dt: As ...``) into one line, in place (before napoleon).
    """
    entry: int | None = None
    i = 0
    while i < len(lines):
        section = _SECTION.match(lines[i])
        if section:
            entry = None
        elif entry is None and i > 0 and _SECTION.match(lines[i - 1]):
            entry = _indent(lines[i])
        line = lines[i]
        if (
            entry is not None
            and line.strip()
            and _indent(line) == entry
            and ":" not in line
            and line.rstrip().endswith(",")
            and i + 1 < len(lines)
        ):
            lines[i : i + 2] = [line.rstrip() + " " + lines[i + 1].strip()]
            continue
        if entry is not None and line.strip() and _indent(line) < entry:
            entry = None
        i += 1


# -- napoleon: sentences are not types --------------------------------------------------

_TYPE_SEPARATORS = re.compile(r"\s*([,|\[\]])\s*")


def _looks_like_type(text: str) -> bool:
    """Whether ``text`` reads as a type (``int | None``, ``tuple[float, float]``)."""
    compact = _TYPE_SEPARATORS.sub(r"\1", text.strip().strip("`"))
    return bool(compact) and " " not in compact and "(" not in compact


_partition = GoogleDocstring._partition_field_on_colon


def _partition_free_text(self: GoogleDocstring, line: str) -> tuple[str, str, str]:
    before, colon, after = _partition(self, line)
    if getattr(self, "_free_text", False) and colon and not _looks_like_type(before):
        return line, "", ""
    return before, colon, after


def free_text_returns() -> None:
    """A ``Returns:`` section or an attribute's docstring whose first line is a sentence
    with a colon keeps the sentence as its description instead of taking the words
    before the colon for a type.
    """

    def flagged(method: Any) -> Any:
        def wrapper(self: GoogleDocstring, *args: Any, **kwargs: Any) -> Any:
            self._free_text = True  # type: ignore[attr-defined]
            try:
                return method(self, *args, **kwargs)
            finally:
                self._free_text = False  # type: ignore[attr-defined]

        return wrapper

    GoogleDocstring._partition_field_on_colon = _partition_free_text  # type: ignore[method-assign]
    for name in ("_consume_returns_section", "_consume_inline_attribute"):
        setattr(GoogleDocstring, name, flagged(getattr(GoogleDocstring, name)))


# -- references by a shorter path ---------------------------------------------------------


def _documented(env: Any) -> dict[str, Any]:
    """Every documented Python object by its full name."""
    return env.domains["py"].objects


_TAILS: dict[tuple[int, int], dict[str, list[str]]] = {}


def _by_tail(objects: dict[str, Any]) -> dict[str, list[str]]:
    """The documented objects' full names by their last component (built once per set)."""
    key = (id(objects), len(objects))
    if key not in _TAILS:
        _TAILS.clear()
        index: dict[str, list[str]] = {}
        for name in objects:
            index.setdefault(name.rsplit(".", 1)[-1], []).append(name)
        _TAILS[key] = index
    return _TAILS[key]


def _mro_names(module: str | None, cls: str | None) -> list[str]:
    """Full names of ``module.cls`` and its base classes (empty when not importable)."""
    obj = _import(f"{module}.{cls}") if module and cls else None
    return [f"{c.__module__}.{c.__qualname__}" for c in getattr(obj, "__mro__", ())]


def _import(path: str) -> Any:
    """The object at the dotted ``path`` (a module, then attributes), or None."""
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for part in parts[cut:]:
                obj = getattr(obj, part)
        except AttributeError:
            return None
        return obj
    return None


def _canonical(path: str) -> str | None:
    """Where the object at ``path`` is defined (a name a module imports or re-exports
    leads to its definition).
    """
    obj = _import(path)
    if obj is None:
        return None
    owner = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if owner and qualname:
        return f"{owner}.{qualname}"
    return None


def resolve_short_name(app: Any, env: Any, node: Any, contnode: Any) -> Any:
    """Resolve ``node``'s Python reference when exactly one documented object fits it:
    a member of the current class or one of its bases; the definition of a name that
    a module imports (``harness.estimators.distributed.estimator.DistributedEstimator``);
    else the only documented object whose full name ends with the target.
    """
    if node.get("refdomain") != "py":
        return None
    target = node["reftarget"].lstrip("~.")
    if re.fullmatch(_EXTERNAL, target):
        return None
    objects = _documented(env)
    module = node.get("py:module")
    candidates = [
        f"{base}.{target}"
        for base in _mro_names(module, node.get("py:class"))
        if f"{base}.{target}" in objects
    ]
    if not candidates:
        found = _canonical(target) or (_canonical(f"{module}.{target}") if module else None)
        candidates = [found] if found in objects else []
    if not candidates:
        tail = target.rsplit(".", 1)[-1]
        candidates = [n for n in _by_tail(objects).get(tail, []) if n.endswith("." + target)]
    if len(candidates) != 1:
        return None
    full = candidates[0]
    entry = env.domains["py"].objects[full]
    ref = nodes.reference("", "", internal=True)
    ref["refuri"] = app.builder.get_relative_uri(node["refdoc"], entry.docname) + "#" + full
    ref["reftitle"] = full
    ref.append(contnode)
    return ref


def skip_tuple_fields(
    app: Any, what: str, name: str, obj: Any, skip: bool, options: Any
) -> bool | None:
    """Skip a named tuple's field accessors: its docstring's ``Attributes:`` documents
    them.
    """
    if (getattr(obj, "__doc__", None) or "").startswith("Alias for field number"):
        return True
    return None


# -- the reference, from the package tree ------------------------------------------------


def modules(package: str) -> list[str]:
    """``package`` (when its ``__init__`` has a docstring) and its modules, not the
    subpackages' (each subpackage is a page of its own).
    """
    pkg = importlib.import_module(package)
    names = [package] if (pkg.__doc__ or "").strip() else []
    for info in pkgutil.iter_modules(pkg.__path__):
        if not info.ispkg:
            names.append(f"{package}.{info.name}")
    return names


def _summary(module: str) -> str:
    """The first sentence of a module's docstring, on one line."""
    doc = (importlib.import_module(module).__doc__ or "").strip()
    first = " ".join(doc.split("\n\n", 1)[0].split())
    return first.replace("|", "\\|")


class AutoModules(SphinxDirective):
    """``.. automodules:: PACKAGE``: a section with ``automodule`` for the package and
    each of its modules, so a new module joins the reference without an edit here.
    """

    required_arguments = 1

    def run(self) -> list[nodes.Node]:
        """The sections, parsed."""
        lines = []
        for module in modules(self.arguments[0]):
            title = f"``{module}``"
            lines += [title, "-" * len(title), "", f".. automodule:: {module}", ""]
        return nested_parse_to_nodes(self.state, "\n".join(lines), allow_section_headings=True)


class ModulesTable(SphinxDirective):
    """``.. modules-table:: PACKAGE [PACKAGE ...]``: every module with the first
    sentence of its docstring, linked to its reference.
    """

    required_arguments = 1
    optional_arguments = 20

    def run(self) -> list[nodes.Node]:
        """The table, parsed."""
        lines = [".. list-table::", "   :header-rows: 1", "   :widths: 1 3", ""]
        lines += ["   * - module", "     - what it is", ""]
        for package in self.arguments:
            for module in modules(package):
                lines += [f"   * - :mod:`{module}`", f"     - {_summary(module)}", ""]
        return nested_parse_to_nodes(self.state, "\n".join(lines), allow_section_headings=False)


# -- config groups, from conf/ --------------------------------------------------------------

CONF = ROOT / "conf"
"""The project's configs: one directory per config group, one YAML per option."""


def group_options(group: str) -> list[str]:
    """The options of config group ``group`` (the YAML files of ``conf/<group>/``), the
    default of ``conf/closed_loop.yaml`` first, then in alphabetical order.
    """
    names = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
    default = group_default(group)
    return sorted(names, key=lambda name: (name != default, name))


def group_default(group: str) -> str | None:
    """The option ``conf/closed_loop.yaml``'s defaults list chooses for ``group``."""
    primary = yaml.safe_load((CONF / "closed_loop.yaml").read_text()) or {}
    for entry in primary.get("defaults") or []:
        if isinstance(entry, dict) and group in entry:
            return str(entry[group])
    return None


def option_comment(group: str, option: str) -> str:
    """The leading comment of ``conf/<group>/<option>.yaml`` (its lines before the first
    that is not a comment, without ``# @package``), as one paragraph.
    """
    words = []
    for line in (CONF / group / f"{option}.yaml").read_text().splitlines():
        if not line.startswith("#"):
            break
        text = line.lstrip("#").strip()
        if not text.startswith("@package"):
            words.append(text)
    return " ".join(w for w in words if w)


def option_target(group: str, option: str) -> str | None:
    """The ``_target_`` of ``conf/<group>/<option>.yaml`` (at its top, or under the
    group's key for an option that writes to the global package).
    """
    node = yaml.safe_load((CONF / group / f"{option}.yaml").read_text()) or {}
    inner = node.get(group) if isinstance(node.get(group), dict) else {}
    target = node.get("_target_") or inner.get("_target_")
    return str(target) if target else None


_CODE = re.compile(r"`([^`]+)`")
"""A backtick span of a comment: code."""


def text_nodes(text: str) -> list[nodes.Node]:
    """``text`` as plain text with its backtick spans as inline literals (nothing else
    in it is markup: a comment's ``*`` and ``_`` stay as they are).
    """
    parts = _CODE.split(text)
    return [nodes.literal(p, p) if i % 2 else nodes.Text(p) for i, p in enumerate(parts) if p]


def _row(cells: list[list[nodes.Node]]) -> nodes.row:
    """A table row, one entry per cell (a list of inline nodes)."""
    row = nodes.row()
    for cell in cells:
        entry = nodes.entry()
        paragraph = nodes.paragraph()
        paragraph.extend(cell)
        entry += paragraph
        row += entry
    return row


def _table(header: list[str], rows: list[list[list[nodes.Node]]]) -> nodes.table:
    """A table node with ``header`` and ``rows`` (each cell a list of inline nodes)."""
    table = nodes.table()
    group = nodes.tgroup(cols=len(header))
    table += group
    for _ in header:
        group += nodes.colspec(colwidth=1)
    head = nodes.thead()
    head += _row([[nodes.Text(h)] for h in header])
    group += head
    body = nodes.tbody()
    for cells in rows:
        body += _row(cells)
    group += body
    return table


def _attribute_text(value: Any) -> str:
    """A class attribute as a table cell: ``yes``/``no`` for a flag, ``-`` for none."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    return "-" if value is None or value == "" else str(value)


class ConfigOptions(SphinxDirective):
    """``.. config-options:: GROUP``: a table of the options of config group ``GROUP``,
    one row per YAML of ``conf/GROUP/`` (:func:`group_options`): the option, its class
    (``_target_``, linked to its reference) and its YAML's leading comment; the option
    ``:attributes: NAME NAME`` adds a column per class attribute (a flag as yes/no).
    """

    required_arguments = 1
    option_spec: ClassVar[dict[str, Any]] = {"attributes": directives.unchanged}

    def run(self) -> list[nodes.Node]:
        """The table."""
        group = self.arguments[0]
        attributes = (self.options.get("attributes") or "").replace(",", " ").split()
        rows = []
        for option in group_options(group):
            target = option_target(group, option)
            linked: list[nodes.Node] = [nodes.Text("-")]
            if target is not None:
                linked = [self.class_reference(target)]
            default = " (default)" if option == group_default(group) else ""
            cells = [[nodes.literal(option, option), nodes.Text(default)], linked]
            cells.append(text_nodes(option_comment(group, option)))
            cls = _import(target) if target else None
            for name in attributes:
                cells.append([nodes.Text(_attribute_text(getattr(cls, name, None)))])
            rows.append(cells)
        header = ["option", "class", "what it is", *(a.replace("_", " ") for a in attributes)]
        return [_table(header, rows)]

    def class_reference(self, target: str) -> nodes.Node:
        """A reference to the class ``target`` (as ``:class:`` makes; nitpicky mode
        reports a class the reference does not document).
        """
        ref = addnodes.pending_xref(
            "",
            nodes.literal(target, target, classes=["xref", "py", "py-class"]),
            refdomain="py",
            reftype="class",
            reftarget=target,
            refexplicit=False,
            refwarn=True,
        )
        ref["refdoc"] = self.env.docname
        return ref


def options_role(
    name: str, rawtext: str, text: str, lineno: int, inliner: Any, options: Any = None,
    content: Any = None,
) -> tuple[list[nodes.Node], list[Any]]:  # fmt: skip
    """``{options}`GROUP```: the options of config group ``GROUP`` as inline literals
    separated by commas, the default marked (:func:`group_options`).
    """
    out: list[nodes.Node] = []
    default = group_default(text)
    for i, option in enumerate(group_options(text)):
        if i:
            out.append(nodes.Text(", "))
        out.append(nodes.literal(option, option))
        if option == default:
            out.append(nodes.Text(" (default)"))
    if not out:
        message = inliner.reporter.error(f"no options in conf/{text}/", line=lineno)
        return [inliner.problematic(rawtext, rawtext, message)], [message]
    return out, []


def setup(app: Any) -> dict[str, bool]:
    """Connect the hooks above."""
    free_text_returns()
    app.add_directive("automodules", AutoModules)
    app.add_directive("modules-table", ModulesTable)
    app.add_directive("config-options", ConfigOptions)
    app.add_role("options", options_role)
    app.connect("autodoc-process-docstring", joined_names, priority=400)
    app.connect("autodoc-process-docstring", plain_text_docstring, priority=600)
    app.connect("autodoc-skip-member", skip_tuple_fields)
    app.connect("missing-reference", resolve_short_name)
    return {"parallel_read_safe": True}
