"""What trainers' loaders read in an AGOS-Dataset directory, beside ``export.jsonl`` (docs/DATASET.md,
"Loading it").

- ``episodes/<episode>/export.parquet`` (:func:`write_episode_parquet`, written when the episode is
  assembled, so it is in ``files.sha256`` and appears with the episode in one rename): the episode's
  export lines, UAV then UGV, with each image's bytes embedded as a Hugging Face ``Image`` (``{"bytes",
  "path"}``, the path relative to the dataset directory) and the ``datasets`` features in the schema's
  metadata. ``datasets.load_dataset(DIR)`` reads these through the card's ``configs``; a directory can
  be moved or uploaded as it is, since no image is found by a path.
- ``dataset_info.json`` (:func:`llamafactory_info`): LLaMA-Factory's entry for ``export.jsonl`` (sharegpt,
  ``messages`` and ``images`` columns, the role tags the export uses); with ``dataset_dir=DIR`` its
  image paths resolve against ``DIR`` (LLaMA-Factory's ``media_dir`` defaults to ``dataset_dir``).
- ``README.md`` (:func:`dataset_card`): the Hugging Face dataset card: YAML header (licence, task,
  sizes, ``configs`` and ``dataset_info`` with the features: ``default``, images as ``Image``, and
  ``raw``, the same files with images as bytes, :data:`RAW_CONFIG`), then how it was built, its sizes,
  how to rebuild it and how to load it.

Only pyarrow (a dependency of agos through rerun-sdk) is needed to write them; ``datasets`` is not.
"""

from __future__ import annotations

import json
import shlex
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from agos.deploy.dataset import DEFAULT_CAPTURE_EVERY_M
from agos.runtime.episode_config import DEFAULT_LOOK
from agos.runtime.schemas import DIFFICULTIES

PARQUET = "export.parquet"
LLAMAFACTORY_INFO = "dataset_info.json"
CARD = "README.md"
DATASET_NAME = "agos"
"""The entry's name in ``dataset_info.json`` (LLaMA-Factory's ``dataset: agos``)."""
HF_SPLIT = "train"
"""The Hugging Face split every build is: the one split LLaMA-Factory, ms-swift and ``datasets`` read by
default. Which agos split file it was built from is in the card and the manifest."""
LICENSE = "apache-2.0"

_STRING = {"dtype": "string", "_type": "Value"}
FEATURES: dict[str, Any] = {
    "id": _STRING, "episode_id": _STRING, "role": _STRING, "decision_index": {"dtype": "int64", "_type": "Value"},
    "stage": _STRING, "legal_actions": [_STRING], "messages": [{"role": _STRING, "content": _STRING}],
    "images": [{"_type": "Image"}],
}
"""The ``datasets`` features of an export row, in the form ``Features.from_dict`` reads in datasets 3.x
and later (a Python list is a list feature)."""
CARD_FEATURES: list[dict[str, Any]] = [
    {"name": "id", "dtype": "string"}, {"name": "episode_id", "dtype": "string"}, {"name": "role", "dtype": "string"},
    {"name": "decision_index", "dtype": "int64"}, {"name": "stage", "dtype": "string"},
    {"name": "legal_actions", "list": "string"},
    {"name": "messages", "list": [{"name": "role", "dtype": "string"}, {"name": "content", "dtype": "string"}]},
    {"name": "images", "list": "image"},
]
"""The same features as the card's YAML writes them (``Features._to_yaml_list``)."""
RAW_CONFIG = "raw"
"""The card's second configuration: the same files, ``images`` as ``{"bytes", "path"}`` structs rather
than ``Image``, so nothing decodes them. ms-swift reads it as ``--dataset DIR:raw``: the configuration
``default`` is decoded by ``datasets`` inside ms-swift's preprocessing and written back, and JPEGs come
out re-encoded (bench/dataset_loaders.py measures it); ``raw`` keeps the files' bytes."""
RAW_FEATURES = [*CARD_FEATURES[:-1], {"name": "images", "list": [{"name": "bytes", "dtype": "binary"},
                                                                  {"name": "path", "dtype": "string"}]}]
SIZE_CATEGORIES = ((1_000, "n<1K"), (10_000, "1K<n<10K"), (100_000, "10K<n<100K"), (1_000_000, "100K<n<1M"),
                   (10_000_000, "1M<n<10M"))


class LoadingFilesError(RuntimeError):
    """pyarrow is missing; the message is one line saying how to install it."""


def _pyarrow() -> tuple[Any, Any]:
    try:
        import pyarrow as pa  # type: ignore[import-untyped]
        import pyarrow.parquet as pq  # type: ignore[import-untyped]
    except ImportError:
        raise LoadingFilesError("agos dataset build writes each episode's export.parquet with pyarrow, which is not "
                                "installed here: pip install pyarrow (or agos[hub])") from None
    return pa, pq


def check_pyarrow() -> None:
    """Raise :class:`LoadingFilesError` now, before a build starts, when pyarrow cannot be imported."""
    _pyarrow()


def write_episode_parquet(lines: Sequence[dict[str, Any]], image_root: Path, rel_prefix: str, out: Path) -> int:
    """Write ``lines`` (export lines, in order) to ``out`` with their images embedded; the rows written.
    Each line's image paths start with ``rel_prefix`` (``episodes/<episode>/``) and are read from
    ``image_root`` (where that directory is now: an attempt under ``.partial`` or the assembled one)."""
    pa, pq = _pyarrow()
    string, message = pa.string(), pa.struct([("role", pa.string()), ("content", pa.string())])
    image = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    schema = pa.schema([("id", string), ("episode_id", string), ("role", string), ("decision_index", pa.int64()),
                        ("stage", string), ("legal_actions", pa.list_(string)), ("messages", pa.list_(message)),
                        ("images", pa.list_(image))],
                       metadata={"huggingface": json.dumps({"info": {"features": FEATURES}})})
    columns: dict[str, list[Any]] = {name: [] for name in schema.names}
    cache: dict[str, bytes] = {}
    for line in lines:
        for name in ("id", "episode_id", "role", "decision_index", "stage", "legal_actions"):
            columns[name].append(line[name])
        columns["messages"].append([{"role": m["role"], "content": m["content"]} for m in line["messages"]])
        images = []
        for rel in line["images"]:
            if not rel.startswith(rel_prefix):
                raise ValueError(f"{rel}: an image outside {rel_prefix}")
            if rel not in cache:
                cache[rel] = (image_root / rel[len(rel_prefix):]).read_bytes()
            images.append({"bytes": cache[rel], "path": rel})
        columns["images"].append(images)
    table = pa.table(columns, schema=schema)
    tmp = out.with_name(f".{out.name}.tmp")
    pq.write_table(table, tmp, compression="zstd")  # zstd: the text shrinks; the images are JPEG/PNG already
    tmp.replace(out)
    return table.num_rows


def llamafactory_info() -> dict[str, Any]:
    """``dataset_info.json``: LLaMA-Factory's entry for ``export.jsonl`` (parser.py ``DatasetAttr``; the
    converter strips a first ``system`` turn, then wants user/assistant alternating)."""
    return {DATASET_NAME: {
        "file_name": "export.jsonl", "formatting": "sharegpt",
        "columns": {"messages": "messages", "images": "images"},
        "tags": {"role_tag": "role", "content_tag": "content", "user_tag": "user", "assistant_tag": "assistant",
                 "system_tag": "system"},
    }}


def size_category(n: int) -> str:
    return next((name for limit, name in SIZE_CATEGORIES if n < limit), "n>10M")


def card_header(manifest: dict[str, Any], parquet: dict[str, int]) -> dict[str, Any]:
    """The card's YAML header as data (what :func:`dataset_card` writes between the ``---`` lines)."""
    return {
        "pretty_name": f"AGOS-Dataset ({Path(manifest['split']).name})",
        "license": LICENSE,
        "language": ["en"],
        "task_categories": ["image-text-to-text", "robotics"],
        "tags": ["multimodal", "embodied-ai", "uav", "ugv", "air-ground-cooperation", "synthetic"],
        "size_categories": [size_category(parquet["rows"])],
        "configs": [{"config_name": name, "data_files": [{"split": HF_SPLIT, "path": f"episodes/*/{PARQUET}"}]}
                    for name in ("default", RAW_CONFIG)],
        "dataset_info": [{"config_name": name, "features": features,
                          "splits": [{"name": HF_SPLIT, "num_bytes": parquet["data_bytes"],
                                      "num_examples": parquet["rows"]}],
                          "download_size": parquet["file_bytes"]}
                         for name, features in (("default", CARD_FEATURES), (RAW_CONFIG, RAW_FEATURES))],
    }


def dataset_card(manifest: dict[str, Any], *, examples: int, export_bytes: int, parquet: dict[str, int]) -> str:
    """``README.md``: the YAML header, then how it was built, its sizes, how to rebuild and load it. It
    names no path but the split's as it was given, so a build's card does not depend on where it ran."""
    c, prov = manifest["counts"], manifest.get("provenance") or {}
    commit = prov.get("commit")
    dirty = prov.get("dirty")
    split = Path(manifest["split"])
    rebuild = ["agos", "dataset", "build", "--split", str(manifest["split"]), "--out", "DIR"]
    if manifest.get("look") != DEFAULT_LOOK:
        rebuild += ["--look", str(manifest.get("look"))]
    if manifest.get("capture_every_m") != DEFAULT_CAPTURE_EVERY_M:
        rebuild += ["--capture-every", f"{manifest.get('capture_every_m'):g}"]
    by_difficulty: dict[str, list[int]] = {}
    for e in manifest["episodes"].values():
        row = by_difficulty.setdefault(e["difficulty"], [0, 0, 0, 0])
        for i, key in enumerate(("decisions", "images", "bytes")):
            row[i + 1] += e[key]
        row[0] += 1
    order = sorted(by_difficulty, key=lambda d: [*DIFFICULTIES, d].index(d))
    towns = sorted({e["town_id"] for e in manifest["episodes"].values()})
    rows = "\n".join(f"| {d} | {r[0]:,} | {r[1]:,} | {r[2]:,} | {r[3]:,} |" for d, r in
                     [(d, by_difficulty[d]) for d in order])
    built = (f"agos commit `{commit}`{' with uncommitted changes' if dirty else ''} (agos {prov.get('agos', '?')})"
             if commit else f"agos {prov.get('agos', '?')} from an installed package (no git commit recorded)")
    mismatch = "" if parquet["rows"] == examples else (
        f" **The Parquet files hold {parquet['rows']:,} rows, not {examples:,}: run the build command again.**")
    body = f"""# AGOS-Dataset: `{split.name}`

Expert trajectories of agos, the air-ground cooperative object search benchmark (a UAV and a UGV
look for a target car in a town), one example per decision of the expert: AGOS-Agent's request at
that point of the trajectory (a system turn, a user turn with `<image>` where each image goes, the
images) answered by the expert's action as reply JSON. The images of every example are embedded in
`episodes/*/export.parquet`; every episode's full record (decisions, poses, depth and semantic images,
the views between decisions, the expert's plan) is under `episodes/<episode>/` (agos's
docs/DATASET.md describes every file).

## How it was built

- By `agos dataset build`, {built}.
- Configuration hash `{manifest['config_hash']}`: look `{manifest.get('look')}`, views every {manifest.get('capture_every_m'):g} m
  between decisions.
- Split file `{split.name}`, sha256 `{manifest['split_sha256']}`.
- {c['episodes']:,} of the split's {c['split']:,} episodes assembled, {c['failed']:,} failed. Towns: {', '.join(towns) or '-'}.
- `manifest.json` lists every episode with the sha256 of its `files.sha256` (`sha256sum -c` works in
  each episode directory).

## Splits and sizes

One Hugging Face split, `{HF_SPLIT}`: every example of this build (a build is one agos split file).

| difficulty | episodes | examples | image files | bytes |
|---|---:|---:|---:|---:|
{rows}
| all | {c['episodes']:,} | {c['decisions']:,} | {c['images']:,} | {c['bytes']:,} |

Examples: {examples:,}, one per decision. `export.jsonl`: {export_bytes:,} bytes. The Parquet files
(the examples with their images embedded): {parquet['file_bytes']:,} bytes, counted in the episodes'
bytes above.{mismatch}

## How to rebuild

With agos at that commit, the same split file (the path as it was given) and the same settings (the
configuration hash above; `{manifest.get('run_dir', 'dataset-*')}/run.json` holds the whole configuration),
`DIR` being this directory or a new one:

```bash
{shlex.join(rebuild)}
```

The same command resumes an interrupted build. `--workers N` changes only the speed.

## How to load it

`DIR` is this directory, wherever it is now.

- **datasets**: `datasets.load_dataset("DIR", split="{HF_SPLIT}")` reads the Parquet files through this
  card's `configs`; `images` is a list of `Image` (PIL images when read). The configuration `{RAW_CONFIG}`
  (`load_dataset("DIR", "{RAW_CONFIG}", ...)`) gives the same rows with each image as its file's bytes.
- **LLaMA-Factory**: `dataset_dir: DIR` and `dataset: {DATASET_NAME}` (the entry in `dataset_info.json`:
  sharegpt, `messages` and `images` of `export.jsonl`; image paths resolve against `dataset_dir`).
- **ms-swift**: `swift sft --dataset DIR:{RAW_CONFIG} ...` from anywhere (the Parquet files, each image's
  bytes as stored), or `cd DIR && swift sft --dataset export.jsonl ...` (ms-swift opens relative image
  paths from the working directory). `--dataset DIR` works too, but ms-swift's preprocessing decodes
  the images and stores them again: JPEGs come out re-encoded.

## Licence

{LICENSE} (the renders, texts and actions are made by agos). Episodes on towns imported from CARLA's
OpenDRIVE maps keep CARLA's road layouts; CARLA's assets are CC-BY 4.0: credit CARLA when you use them.
"""
    return f"---\n{_yaml(card_header(manifest, parquet))}---\n\n{body}"


def _yaml(value: Any, indent: int = 0) -> str:
    """Block-style YAML of dicts, lists and scalars (scalars as JSON, which YAML reads as they are)."""
    pad = " " * indent
    out = []
    if isinstance(value, dict):
        for key, item in value.items():
            if isinstance(item, (dict, list)) and item:
                out.append(f"{pad}{key}:\n{_yaml(item, indent + 2)}")
            else:
                out.append(f"{pad}{key}: {_scalar(item)}\n")
    else:
        for item in value:
            if isinstance(item, (dict, list)) and item:
                inner = _yaml(item, indent + 2)
                out.append(f"{pad}- {inner[indent + 2:]}")
            else:
                out.append(f"{pad}- {_scalar(item)}\n")
    return "".join(out)


def _scalar(value: Any) -> str:
    if isinstance(value, str) and value.replace("-", "").replace("_", "").isalnum() and not value[0].isdigit() \
            and value.lower() not in ("yes", "no", "true", "false", "null", "on", "off", "y", "n"):
        return value
    return json.dumps(value)


def parquet_sizes(paths: Iterable[Path]) -> dict[str, int]:
    """Rows, data bytes (uncompressed, the split's ``num_bytes``) and file bytes of the Parquet files
    that exist among ``paths``, from their footers."""
    _, pq = _pyarrow()
    sizes = {"rows": 0, "data_bytes": 0, "file_bytes": 0}
    for path in paths:
        if path.is_file():
            meta = pq.read_metadata(path)
            sizes["rows"] += meta.num_rows
            sizes["data_bytes"] += sum(meta.row_group(i).total_byte_size for i in range(meta.num_row_groups))
            sizes["file_bytes"] += path.stat().st_size
    return sizes


def write_loading_files(out_dir: Path, manifest: dict[str, Any], export: Path) -> None:
    """``dataset_info.json`` and ``README.md`` for what ``out_dir`` holds now (``manifest``, ``export``)."""
    with export.open("rb") as f:
        examples = sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b""))
    parquet = parquet_sizes(out_dir / "episodes" / name / PARQUET for name in sorted(manifest["episodes"]))
    files = {LLAMAFACTORY_INFO: json.dumps(llamafactory_info(), indent=1) + "\n",
             CARD: dataset_card(manifest, examples=examples, export_bytes=export.stat().st_size,
                                parquet=parquet)}
    for name, text in files.items():
        tmp = out_dir / f".{name}.tmp"
        tmp.write_text(text)
        tmp.replace(out_dir / name)
