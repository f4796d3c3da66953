"""Command-line parsing shared by the example scripts: a dataclass of arguments -> argparse.

Each field becomes ``--field-name`` with the field's default and the string literal under the
field as its help; a ``bool`` field becomes a flag (``store_true``).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect


def field_docs(cls) -> dict[str, str]:
    """The string literal under each field of a dataclass (for --help)."""
    body = ast.parse(inspect.getsource(cls)).body[0].body
    return {
        a.target.id: b.value.value
        for a, b in zip(body, body[1:], strict=False)
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr)
    }


def dataclass_parser(cls, description: str, epilog: str | None = None) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` with one option per field of the dataclass ``cls``."""
    docs = field_docs(cls)
    parser = argparse.ArgumentParser(description=description, epilog=epilog)
    for field in dataclasses.fields(cls):
        flag = f"--{field.name.replace('_', '-')}"
        if field.type in ("bool", bool):
            parser.add_argument(flag, action="store_true", help=docs.get(field.name))
        else:
            kind = type(field.default)
            parser.add_argument(flag, type=kind, default=field.default, help=docs.get(field.name))
    return parser


def device_error(name: str) -> str | None:
    """Why ``--device name`` cannot be used here (an unknown device, or no GPU), or None."""
    import torch

    try:
        device = torch.device(name)
    except (RuntimeError, ValueError) as error:
        return f"--device {name!r} is not a device torch knows: {error}"
    if device.type == "cuda" and not torch.cuda.is_available():
        return f"--device {name!r}: torch sees no CUDA GPU here (use --device cpu)"
    if device.type not in ("cpu", "cuda"):
        return f"--device must be cpu or cuda (e.g. cuda:1), got {name!r}"
    return None
