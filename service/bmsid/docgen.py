"""Generated documentation: the README's tables -- the CAN contract (read from the DBC by
cantools) and the configuration reference (walked from the pydantic settings model and its field
docstrings) -- and the MQTT cell schema (built from ``estimate/fields.py``'s ``CELL_FIELDS``).

    python -m bmsid.docgen            # rewrite the README's blocks and the generated files
    python -m bmsid.docgen --check    # exit 1 when any of them is not current (tests run this)

A block lies between ``<!-- generated:NAME -->`` and ``<!-- end generated:NAME -->``. The schema
is written whole, to ``publish/schemas/cell.json`` (shipped in the package) and to its copy in
``docs/mqtt-schemas/`` beside the README.
"""

from __future__ import annotations

import argparse
import re
import sys
import types
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cantools
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from bmsid.config.settings import Settings
from bmsid.publish import payloads

PACKAGE_DBC = Path(__file__).resolve().parent / "dbc" / "bmsid.dbc"


# ---------------------------------------------------------------------- CAN contract
def _num(x: float) -> str:
    return f"{x:.10g}"


def can_contract_table(dbc_path: Path = PACKAGE_DBC) -> str:
    """One row per signal of bmsid.dbc: direction, id, length, bit layout, scaling, range, unit.

    The ``*_11bit`` twins (same layout on 11-bit ids) are listed once, in the id column.
    """
    db = cantools.database.load_file(str(dbc_path))
    assert isinstance(db, cantools.database.can.Database)
    twins = {
        m.name.removesuffix("_11bit"): m.frame_id for m in db.messages if m.name.endswith("_11bit")
    }
    rows = [
        "| direction | message | id (11-bit twin) | bytes | signal | start bit, length | "
        "scale | range | unit |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for m in db.messages:
        if m.name.endswith("_11bit"):
            continue
        sender = m.senders[0] if m.senders else ""
        direction = "out (bmsid sends)" if sender == "BMSID" else "in (BMS sends)"
        ident = f"0x{m.frame_id:08X}" if m.is_extended_frame else f"0x{m.frame_id:03X}"
        if m.name in twins:
            ident += f" (0x{twins[m.name]:03X})"
        for s in m.signals:
            mux = ""
            if s.is_multiplexer:
                mux = " (multiplexer)"
            elif s.multiplexer_ids:
                mux = f" (mux {s.multiplexer_signal} {_mux_ids(s.multiplexer_ids)})"
            lo = "" if s.minimum is None else _num(s.minimum)
            hi = "" if s.maximum is None else _num(s.maximum)
            sign = "s" if s.is_signed else "u"
            order = "le" if s.byte_order == "little_endian" else "be"
            rows.append(
                f"| {direction} | {m.name} | {ident} | {m.length} | {s.name}{mux} | "
                f"{s.start}, {s.length}{sign} {order} | {_num(s.scale)} | {lo} .. {hi} | "
                f"{s.unit or ''} |"
            )
    return "\n".join(rows) + "\n"


def _mux_ids(ids: list[int]) -> str:
    return f"{ids[0]}" if len(ids) == 1 else f"{min(ids)}..{max(ids)}"


# ---------------------------------------------------------------------- configuration
def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return " \\| ".join(f'"{a}"' for a in typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_name(a) for a in typing.get_args(annotation))
    if origin is typing.Annotated:
        return _type_name(typing.get_args(annotation)[0])
    if annotation is type(None):
        return "none"
    if isinstance(annotation, type):
        return {"SecretStr": "secret", "PosixPath": "path", "Path": "path"}.get(
            annotation.__name__, annotation.__name__
        )
    return str(annotation)


def _default(field: FieldInfo) -> str:
    if field.default is PydanticUndefined and field.default_factory is None:
        return "**required**"
    value = field.get_default(call_default_factory=True)
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str | Path):
        return f'`"{value}"`'
    return f"`{value!r}`"


def _model_class(annotation: Any) -> type[BaseModel] | None:
    for a in (annotation, *typing.get_args(annotation)):
        if isinstance(a, type) and issubclass(a, BaseModel):
            return a
    return None


def _fields(model: type[BaseModel], prefix: str) -> Iterator[tuple[str, FieldInfo, bool]]:
    """(dotted key, field, is_section) depth-first, sections before their keys."""
    for name, field in model.model_fields.items():
        key = f"{prefix}{name}"
        sub = _model_class(field.annotation)
        if sub is not None:
            yield key, field, True
            yield from _fields(sub, key + ".")
        else:
            yield key, field, False


def _one_line(text: str | None) -> str:
    return re.sub(r"\s+", " ", text or "").strip().replace("|", "\\|")


def config_reference_table(model: type[BaseModel] = Settings) -> str:
    """Every key of the daemon's TOML, with type, default, environment variable and meaning."""
    rows = [
        "| key | type | default | environment | meaning |",
        "|---|---|---|---|---|",
    ]
    for key, field, section in _fields(model, ""):
        env = "BMSID_" + key.upper().replace(".", "__")
        if section:
            sub = _model_class(field.annotation)
            doc = _one_line(field.description or (sub.__doc__ if sub else ""))
            rows.append(f"| **`[{key}]`** | section | | | {doc} |")
            continue
        rows.append(
            f"| `{key}` | {_type_name(field.annotation)} | {_default(field)} | `{env}` | "
            f"{_one_line(field.description)} |"
        )
    return "\n".join(rows) + "\n"


# ---------------------------------------------------------------------- README blocks
GENERATORS: dict[str, Callable[[], str]] = {
    "can-contract": can_contract_table,
    "config-reference": config_reference_table,
}


def render(readme: str) -> str:
    """``readme`` with every generated block replaced by its current content."""
    for name, make in GENERATORS.items():
        begin, end = f"<!-- generated:{name} -->", f"<!-- end generated:{name} -->"
        pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.DOTALL)
        if not pattern.search(readme):
            raise ValueError(f"README has no block {begin} ... {end}")
        body = f"{begin}\n<!-- python -m bmsid.docgen writes this table -->\n{make()}{end}"
        readme = pattern.sub(lambda _m: body, readme)  # noqa: B023 (used at once)
    return readme


# ---------------------------------------------------------------------- whole files
def generated_files(repo: Path) -> dict[Path, str]:
    """Path -> content of every file generated whole; ``repo`` is the README's directory."""
    cell = payloads.schema_text(payloads.cell_schema())
    out = {payloads.CELL_SCHEMA_PATH: cell}
    docs = repo / "docs" / "mqtt-schemas"
    if docs.is_dir():  # a source checkout; an installed package has no docs/
        out[docs / "cell.json"] = cell
    return out


def stale_files(repo: Path) -> dict[Path, str]:
    """The generated files whose content on disk is not current (path -> what it should be)."""
    return {
        path: text
        for path, text in generated_files(repo).items()
        if not path.is_file() or path.read_text(encoding="utf-8") != text
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--readme", type=Path, default=Path("README.md"))
    ap.add_argument(
        "--check", action="store_true", help="exit 1 if anything generated is not current"
    )
    args = ap.parse_args(argv)
    text = args.readme.read_text(encoding="utf-8")
    new = render(text)
    stale = stale_files(args.readme.resolve().parent)
    if args.check:
        for path in stale:
            print(f"{path}: stale; run: python -m bmsid.docgen")
        if new != text:
            print(f"{args.readme}: generated tables are stale; run: python -m bmsid.docgen")
        if stale or new != text:
            return 1
        print(f"{args.readme}: generated tables are current")
        return 0
    if new != text:
        args.readme.write_text(new, encoding="utf-8")
        print(f"updated {args.readme}")
    for path, content in stale.items():
        path.write_text(content, encoding="utf-8")
        print(f"updated {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
