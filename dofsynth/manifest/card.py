"""The dataset card of a finished set: `OUT/README.md` with the Hugging Face YAML header (its
configs and data files per split, features, licence) and a body that says what the set holds,
and `OUT/record.schema.json`, the JSON Schema of its records (dofsynth.record).

The features are those `datasets.load_dataset("webdataset", data_dir=OUT)` infers (a test keeps
them equal): PNG members are images, EXR members bytes, the record a struct whose fields have
one type in every record (schema 4), `__key__` and `__url__` strings. So `load_dataset(OUT)`,
which reads the card, and the plain webdataset loader give the same columns.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from dofsynth.files import atomic_write_bytes
from dofsynth.record import RECORD_SCHEMA_FILE, record_schema
from dofsynth.shards import read_shard

CARD_NAME = "README.md"


def _dtype(value):
    """The Hugging Face feature of one JSON value (the YAML form of datasets.Features)."""
    if isinstance(value, bool):
        return {"dtype": "bool"}
    if isinstance(value, int):
        return {"dtype": "int64"}
    if isinstance(value, float):
        return {"dtype": "float64"}
    if isinstance(value, str):
        return {"dtype": "string"}
    if value is None:
        return {"dtype": "null"}
    if isinstance(value, dict):
        return {"struct": [{"name": k, **_dtype(v)} for k, v in sorted(value.items())]}
    inner = _dtype(value[0]) if value else {"dtype": "null"}
    return {"list": inner.get("dtype") or inner.get("struct") or inner}


def features(members: dict[str, bytes]) -> list[dict]:
    """The features of a set from one of its samples ({suffix: bytes}), in tar member order."""
    out = []
    for name in sorted(members):
        if name.endswith(".png"):
            out.append({"name": name, "dtype": "image"})
        elif name == "json":
            out.append({"name": name, **_dtype(json.loads(members[name]))})
        else:
            out.append({"name": name, "dtype": "binary"})
    return out + [{"name": "__key__", "dtype": "string"}, {"name": "__url__", "dtype": "string"}]


def _yaml(obj, indent: int = 0) -> list[str]:
    """Block YAML of nested dicts, lists and scalars (strings quoted as JSON, which YAML reads)."""
    pad, lines = " " * indent, []
    if isinstance(obj, dict):
        for k, v in obj.items():
            if isinstance(v, (dict, list)) and v:
                lines += [f"{pad}{k}:"] + _yaml(v, indent + 2)
            else:
                lines.append(f"{pad}{k}: {_scalar(v)}")
    else:
        for item in obj:
            sub = _yaml(item, indent + 2) if isinstance(item, (dict, list)) else [f"{pad}  {_scalar(item)}"]
            lines.append(f"{pad}- {sub[0].lstrip()}")
            lines += sub[1:]
    return lines


def _scalar(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if v is None:
        return "null"
    if v == [] or v == {}:
        return "[]" if v == [] else "{}"
    return json.dumps(str(v))


def dataset_card(manifest: dict, first_sample: dict[str, bytes]) -> str:
    """README.md of a set: the YAML header and a body (what, how to load, licences, files)."""
    rec = manifest["recipe"]
    splits = manifest["splits"]
    licences = manifest.get("licences", {})
    header = {
        "pretty_name": f"dofsynth {rec['name']}",
        "license": "other",
        "tags": ["depth-of-field", "bokeh", "synthetic", "webdataset", "dofsynth"],
        "configs": [{"config_name": "default",
                     "data_files": [{"split": s, "path": f"{s}/*.tar"} for s in splits]}],
        "dataset_info": {"features": features(first_sample),
                         "splits": [{"name": s, "num_examples": b["samples"], "num_bytes": b["bytes"]}
                                    for s, b in splits.items()]},
    }
    fmt = manifest.get("format", {})
    lines = ["---", *_yaml(header), "---", "",
             f"# dofsynth {rec['name']}", "",
             "Synthetic shallow depth-of-field samples made by dofsynth "
             f"{manifest['dofsynth_version']} from the recipe `{rec['name']}` (sha256 {rec['sha256']}): one "
             "background photo and two foreground cutouts on three depth planes, each plane blurred on its own in "
             f"linear light and composited back to front (renderer {fmt.get('renderer', '?')}).", "",
             "| split | samples | shards | bytes |", "|---|---|---|---|"]
    lines += [f"| {s} | {b['samples']} | {len(b['shards'])} | {b['bytes']} |" for s, b in splits.items()]
    lines += ["", "## Loading", "", "```python",
              "import datasets",
              "ds = datasets.load_dataset(\"webdataset\", data_dir=\"OUT\")   # or datasets.load_dataset(\"OUT\")",
              "", "import webdataset as wds",
              "from dofsynth.record import exr_handler",
              "ds = wds.WebDataset(\"OUT/train/train-{000000..000009}.tar\").decode(\"rgb\", exr_handler)",
              "```", "", "EXR members (normalized disparity; optional CoC maps and layers) are bytes to "
              "`datasets`; `dofsynth.record.exr_handler` or OpenEXR decodes them.", "",
              "## Members", "", "| member | type | dtype | channels | range | meaning |", "|---|---|---|---|---|---|"]
    lines += [f"| `KEY.{m['name']}` | {m['type']} | {m['dtype']} | {m['channels']} | {m['range']} | {m['meaning']} |"
              for m in fmt.get("members", [])]
    lines += ["", f"The record (`KEY.json`) follows `{RECORD_SCHEMA_FILE}` beside this card (JSON Schema "
              f"draft 2020-12, record schema {fmt.get('record_schema_version', '?')}); conventions:", ""]
    lines += [f"- {k}: {v}" for k, v in sorted(fmt.get("conventions", {}).items())]
    lines += ["", "## Licences", "", "Each sample is made from three assets; their licences (samples using "
              "an asset under each):", ""]
    lines += [f"- {lic}: {b['samples']} samples" for lic, b in licences.items()] or ["- (not recorded)"]
    lines += ["", "## Contact sheet", "",
              "`dofsynth sheet OUT` draws `sheet-test.png` (one row per sample: all-in-focus image, disparity, "
              "coverage, every target); `dofsynth sheet OUT --html OUT/page` a QA page.", "",
              "![contact sheet](sheet-test.png)", ""]
    return "\n".join(lines)


def write_card(out: str | os.PathLike, manifest: dict) -> Path:
    """Write OUT/README.md and OUT/record.schema.json for a finished set (atomically)."""
    out = Path(out)
    first = next(((s, b["shards"][0]) for s, b in manifest["splits"].items() if b["shards"]), None)
    if first is None:
        raise ValueError(f"{out}: a data set without shards has no card")
    _, members = next(read_shard(out / first[1]["path"]))
    atomic_write_bytes(out / RECORD_SCHEMA_FILE, (json.dumps(record_schema(), indent=1) + "\n").encode())
    path = out / CARD_NAME
    atomic_write_bytes(path, dataset_card(manifest, members).encode("utf-8"))
    return path
