"""A configuration as YAML with each field's description as a comment above it.

The text loads back into the same configuration (``load_config`` ignores comments).
"""

from __future__ import annotations

import textwrap

import yaml
from pydantic import BaseModel

_WIDTH = 88


def _scalar(value) -> str:
    """One YAML value on one line (flow style for lists and mappings)."""
    text = yaml.safe_dump(value, default_flow_style=True, width=10**6, sort_keys=False).strip()
    return text[: -len("...")].strip() if text.endswith("...") else text


def _comment(text: str, indent: str) -> list[str]:
    words = " ".join(text.split())
    return [f"{indent}# {line}" for line in textwrap.wrap(words, _WIDTH - len(indent) - 2)]


def _lines(model: BaseModel, data: dict, indent: str) -> list[str]:
    out: list[str] = []
    for name, field in type(model).model_fields.items():
        value = getattr(model, name)
        if field.description:
            out += _comment(field.description, indent)
        if isinstance(value, BaseModel):
            out.append(f"{indent}{name}:")
            out += _lines(value, data[name], indent + "  ")
        else:
            out.append(f"{indent}{name}: {_scalar(data[name])}")
    return out


def dump_config(config: BaseModel) -> str:
    """YAML text of a config (paths as strings), every field preceded by its description."""
    return "\n".join(_lines(config, config.model_dump(mode="json"), "")) + "\n"


def missing_descriptions(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Dotted names of the fields of ``model`` (recursively) that have no description."""
    missing = []
    for name, field in model.model_fields.items():
        dotted = f"{prefix}{name}"
        if not field.description:
            missing.append(dotted)
        sub = field.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            missing += missing_descriptions(sub, dotted + ".")
    return missing
