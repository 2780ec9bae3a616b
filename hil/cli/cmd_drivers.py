"""``hil drivers [--json]``: every available driver with its kind, origin and config fields."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from pydantic import BaseModel

from plugins.manager import HilPlugins
from plugins.registry import DriverRegistry


def _type_name(annotation: Any) -> str:
    text = getattr(annotation, "__name__", None) if isinstance(annotation, type) else None
    return text or str(annotation).replace("typing.", "")


def config_fields(model: type[BaseModel]) -> list[dict[str, Any]]:
    """The fields of a driver config model: name, type, default (or required), description."""
    out = []
    for name, field in model.model_fields.items():
        required = field.is_required()
        default: Any = None
        if not required:
            value = field.get_default(call_default_factory=True)
            default = value.model_dump(mode="json") if isinstance(value, BaseModel) else value
            if isinstance(default, tuple):
                default = json.loads(json.dumps(default, default=_jsonable))
        out.append({"name": name, "type": _type_name(field.annotation), "required": required,
                    "default": json.loads(json.dumps(default, default=_jsonable)),
                    "description": field.description or ""})
    return out


def _jsonable(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    return str(value)


def describe(registry: DriverRegistry, plugins: list[str]) -> dict[str, Any]:
    """JSON-ready description of every registered (and unavailable) driver."""
    return {
        "plugins": plugins,
        "drivers": [
            {"kind": d.kind, "name": d.name, "origin": d.origin, "simulated": d.simulated,
             "description": d.description, "config_model": d.config_model.__name__,
             "fields": config_fields(d.config_model)}
            for d in registry.drivers()
        ],
        "unavailable": [
            {"kind": u.kind, "name": u.name, "origin": u.origin, "module": u.module, "reason": u.reason}
            for u in registry.unavailable()
        ],
    }


def _print_text(desc: dict[str, Any]) -> None:
    out = sys.stdout
    for d in desc["drivers"]:
        sim = ", simulated" if d["simulated"] else ""
        print(f"{d['kind']:8s} {d['name']:16s} ({d['origin']}{sim}) {d['description']}", file=out)
        for f in d["fields"]:
            if f["name"] == "driver":
                continue
            dflt = "required" if f["required"] else f"default {json.dumps(f['default'])}"
            desc_txt = f"  {f['description']}" if f["description"] else ""
            print(f"    {f['name']}: {f['type']} = {dflt}{desc_txt}", file=out)
    for u in desc["unavailable"]:
        print(f"{u['kind']:8s} {u['name']:16s} ({u['origin']}, UNAVAILABLE) {u['reason']}", file=out)


def run(args: argparse.Namespace) -> int:
    plugins = HilPlugins()
    desc = describe(plugins.driver_registry(), plugins.plugin_names())
    if args.json:
        json.dump(desc, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        _print_text(desc)
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("drivers", help="list every available driver and its config fields",
                       description="List every driver (built-in and plugin) with its kind, origin "
                                   "and config fields; unavailable drivers say why.")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    p.set_defaults(func=run)
