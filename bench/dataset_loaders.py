"""A built AGOS-Dataset through LLaMA-Factory's and ms-swift's own loading code, and through ``datasets``,
from a copy of the directory in another place (docs/DATASET.md, "Loading it").

Neither framework is installed (both pull in torch, transformers and more). Their loading code runs
from their sources instead: a checkout, or a git directory such as the ``fetch`` tool's mirror (the
script then takes ``HEAD`` with ``git archive``). What is stubbed, and only that:

- the modules ``torch``, ``torchaudio``, ``torchvision``, ``transformers``, ``peft``, ``av``,
  ``modelscope``, ``requests``, ``accelerate``, ``trl``: empty modules whose attributes are mocks
  (imported by the files below, never called on the paths run here; ``datasets`` is imported first, so
  it sees none of them);
- LLaMA-Factory: the package ``__init__`` files are not run (they import the trainers); its
  ``llamafactory.data.processor`` is replaced by an empty module (tokenisation, not loading);
- ms-swift: the package ``__init__`` files are not run; ``swift.utils`` is a small module (a logger,
  ``is_dist`` False, ``use_hf_hub`` False, ``safe_ddp_context`` a no-op) whose ``get_env_args`` is ms-swift's
  own function taken from ``swift/utils/utils.py``; ``swift.hub.get_hub`` gives ``HFHub.load_dataset``
  taken from ``swift/hub/hub.py``; ``swift.template`` gives ``Template._load_image`` taken from
  ``swift/template/base.py`` and the real ``swift/template/vision_utils.py``; ``swift.dataset.dataset``
  (the hub datasets ms-swift registers by name) is left out; ``swift.dataset.utils`` is its own
  ``sample_dataset`` alone, taken from that file.

What runs is theirs: LLaMA-Factory's ``_get_merged_dataset`` (loader.py: ``dataset_info.json`` by
parser.py, ``datasets.load_dataset``, the sharegpt converter) and, per example, the multimodal plugin's
``_validate_messages`` (``<image>`` count = images) and ``_regularize_images`` (opens each image);
ms-swift's ``swift.dataset.loader.load_dataset`` (DatasetSyntax, DatasetLoader, the preprocessors) on
``export.jsonl`` from inside the directory (``cd DIR``), on ``DIR:raw`` and on ``DIR`` (the card's two
configurations of the Parquet files), then the template's ``_load_image`` on every image in both of its
modes. Each route compares every example with ``export.jsonl``: its turns, its images' count and pixel
size; for ms-swift also whether the template gets each file's bytes (``DIR`` is expected not to: the
preprocessing decodes the ``Image`` feature and writes it back, which re-encodes JPEGs).

    .venv/bin/python bench/dataset_loaders.py DIR --llamafactory SRC --ms-swift SRC

Exit 0 when every route loads every line with every image; 1 otherwise.
"""

from __future__ import annotations

import argparse
import ast
import collections
import contextlib
import functools
import importlib
import importlib.abc
import importlib.machinery
import io
import json
import logging
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import textwrap
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import datasets  # before the stubs: datasets decides at import which frameworks exist
import numpy as np
from PIL import Image

STUBBED = ("torch", "torchaudio", "torchvision", "transformers", "peft", "av", "modelscope", "requests",
           "accelerate", "trl")


class _Stub(types.ModuleType):
    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        value = mock.MagicMock(name=f"{self.__name__}.{name}")
        setattr(self, name, value)
        return value


class _StubFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, name: str, path: Any, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if name.split(".")[0] in STUBBED:
            return importlib.machinery.ModuleSpec(name, self, is_package=True)
        return None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        module = _Stub(spec.name)
        module.__path__ = []
        return module

    def exec_module(self, module: types.ModuleType) -> None:
        pass


@contextlib.contextmanager
def _stubs() -> Iterator[None]:
    """The stubbed modules while the frameworks' files are imported; gone afterwards (``datasets`` looks
    for ``torch`` in ``sys.modules`` when it hashes and pickles)."""
    finder = _StubFinder()
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)
        for name in [n for n, m in sys.modules.items() if isinstance(m, _Stub)]:
            del sys.modules[name]


def _module(name: str, path: Path | None = None, **attrs: Any) -> types.ModuleType:
    """A module put in ``sys.modules`` as it is: a package over ``path`` whose ``__init__`` never runs."""
    module = types.ModuleType(name)
    if path is not None:
        module.__path__ = [str(path)]
    for key, value in attrs.items():
        setattr(module, key, value)
    sys.modules[name] = module
    return module


def _function(source: Path, name: str, namespace: dict[str, Any], cls: str | None = None) -> Any:
    """The function ``name`` (a method of ``cls``, its decorators dropped) of a source file, defined in
    ``namespace`` (which gets the ``typing`` names its annotations use)."""
    namespace = {**{k: getattr(typing, k) for k in typing.__all__}, "_T": typing.TypeVar("_T"), **namespace}
    tree = ast.parse(source.read_text())
    body = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls).body if cls else tree.body
    node = next(n for n in body if isinstance(n, ast.FunctionDef) and n.name == name)
    node.decorator_list = []
    exec(compile(ast.Module(body=[node], type_ignores=[]), str(source), "exec"), namespace)
    return namespace[name]


def _sources(src: Path, inner: str, work: Path) -> Path:
    """A tree holding ``inner``: ``src`` itself, or ``HEAD`` of the git directory ``src`` unpacked."""
    if (src / inner).is_dir():
        return src
    out = work / src.name.replace("+", "_")
    out.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "--git-dir", str(src), "archive", "HEAD", inner], check=True,
                             capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(out, filter="data")
    commit = subprocess.run(["git", "--git-dir", str(src), "rev-parse", "HEAD"], check=True, capture_output=True,
                            text=True).stdout.strip()
    print(f"  sources: {src} at {commit}")
    return out


@contextlib.contextmanager
def _cwd(path: Path) -> Iterator[None]:
    before = Path.cwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(before)


class Tally:
    """What a route loaded, against ``export.jsonl``."""

    def __init__(self, route: str, lines: list[dict[str, Any]], root: Path) -> None:
        self.route, self.lines, self.root = route, lines, root
        self.rows = self.images = self.tokens_ok = 0
        self.problems: list[str] = []

    def row(self, k: int, system: str, user: str, assistant: str, images: list[Image.Image]) -> None:
        line = self.lines[k]
        want = [m["content"] for m in line["messages"]]
        if [system, user, assistant] != want:
            self.problems.append(f"line {k + 1} ({line['id']}): turns differ")
        if user.count("<image>") == len(images) == len(line["images"]):
            self.tokens_ok += 1
        else:
            self.problems.append(f"line {k + 1}: {user.count('<image>')} <image>, {len(images)} images")
        for image, rel in zip(images, line["images"], strict=False):
            with Image.open(self.root / rel) as ref:
                if image.size != ref.size:
                    self.problems.append(f"line {k + 1}: {rel} is {image.size}, the file {ref.size}")
        self.rows += 1
        self.images += len(images)

    def report(self) -> bool:
        want_images = sum(len(x["images"]) for x in self.lines)
        ok = not self.problems and self.rows == len(self.lines) and self.images == want_images
        print(f"  {self.route}: {self.rows} of {len(self.lines)} lines, {self.images} of {want_images} images "
              f"opened, <image> count = images in {self.tokens_ok}: {'OK' if ok else 'FAILED'}")
        for problem in self.problems[:10]:
            print(f"    {problem}")
        return ok


# ----- LLaMA-Factory ----------------------------------------------------------------------------------
def llamafactory(src: Path, data: Path, lines: list[dict[str, Any]], work: Path) -> bool:
    root = _sources(src, "src/llamafactory", work) / "src" / "llamafactory"
    _module("llamafactory", root)
    _module("llamafactory.data", root / "data")
    _module("llamafactory.extras", root / "extras")
    _module("llamafactory.extras.misc", use_modelscope=lambda: False, use_openmind=lambda: False,
            check_version=lambda *a, **k: None, has_tokenized_data=lambda path: False)
    _module("llamafactory.data.processor", **{name: type(name, (), {}) for name in (
        "FeedbackDatasetProcessor", "PackedSupervisedDatasetProcessor", "PairwiseDatasetProcessor",
        "PretrainDatasetProcessor", "SupervisedDatasetProcessor", "UnsupervisedDatasetProcessor")})
    with _stubs():
        loader = importlib.import_module("llamafactory.data.loader")
        mm_plugin = importlib.import_module("llamafactory.data.mm_plugin")

    data_args = types.SimpleNamespace(dataset_dir=str(data), media_dir=str(data),  # DataArguments: media_dir = dataset_dir
                                      streaming=False, preprocessing_num_workers=None, overwrite_cache=True,
                                      max_samples=None, mix_strategy="concat", interleave_probs=None)
    model_args = types.SimpleNamespace(cache_dir=str(work / "hf-cache"), hf_hub_token=None)
    training_args = types.SimpleNamespace(local_process_index=0, seed=42, dataloader_num_workers=0)
    dataset = loader._get_merged_dataset(["agos"], model_args, data_args, training_args, stage="sft")
    plugin = mm_plugin.BasePlugin(image_token="<image>", video_token=None, audio_token=None)
    tally = Tally("LLaMA-Factory, dataset_dir=DIR, dataset=agos", lines, data)
    outside = 0
    for k, row in enumerate(dataset):
        if not row["_prompt"] or not row["_response"]:
            tally.problems.append(f"line {k + 1}: dropped by the converter")
            continue
        images = row["_images"] or []
        outside += sum(1 for p in images if not (os.path.isfile(p) and Path(p).is_relative_to(data)))
        plugin._validate_messages(row["_prompt"] + row["_response"], images, [], [])  # raises on a mismatch
        opened = plugin._regularize_images(images, image_max_pixels=1 << 30, image_min_pixels=1)["images"]
        tally.row(k, row["_system"], row["_prompt"][0]["content"], row["_response"][0]["content"], opened)
    if outside:
        tally.problems.append(f"{outside} image paths not resolved to files under {data}")
    return tally.report()


# ----- ms-swift ---------------------------------------------------------------------------------------
def ms_swift(src: Path, data: Path, lines: list[dict[str, Any]], work: Path) -> bool:
    root = _sources(src, "swift", work) / "swift"
    log = logging.getLogger("swift")
    for name in ("info_once", "warning_once", "info_if"):
        setattr(log, name, lambda *a, **k: None)
    env_ns: dict[str, Any] = {"os": os, "logger": log, "strtobool": lambda v: v.lower() in ("1", "true", "yes")}
    get_env_args = _function(root / "utils" / "utils.py", "get_env_args", env_ns)
    _module("swift", root)
    _module("swift.utils", get_logger=lambda *a, **k: log, is_dist=lambda: False, is_master=lambda: True,
            use_hf_hub=lambda: False, safe_ddp_context=lambda *a, **k: contextlib.nullcontext(),
            get_seed=lambda *a, **k: 42, download_ms_file=None, get_env_args=get_env_args)
    hf_load = functools.partial(_function(root / "hub" / "hub.py", "load_dataset", {}, cls="HFHub"), None)  # cls
    _module("swift.hub", get_hub=lambda use_hf=None: types.SimpleNamespace(load_dataset=hf_load))
    template = _module("swift.template", root / "template", history_to_messages=None, Template=object,
                       MaxLengthError=type("MaxLengthError", (Exception,), {}))
    _module("swift.template.template_inputs", normalize_openai_tool_calls=lambda messages: messages)
    _module("swift.dataset", root / "dataset")
    sample_dataset = _function(root / "dataset" / "utils.py", "sample_dataset",
                               {"np": np, "logger": log, "HfDataset": datasets.Dataset})
    _module("swift.dataset.utils", sample_dataset=sample_dataset)
    _module("swift.dataset.dataset", root / "dataset" / "dataset")  # ms-swift's registered hub datasets: not run
    _module("swift.dataset.dataset.llm", SelfCognitionPreprocessor=None)
    with _stubs():
        importlib.import_module("modelscope.hub.utils")
        _module("modelscope.hub.utils.utils", get_cache_dir=lambda: str(work / "ms-cache"))
        vision_utils = importlib.import_module("swift.template.vision_utils")
        loader = importlib.import_module("swift.dataset.loader")
    load_image_ns = {"os": os, "load_image": vision_utils.load_image}
    load_image = _function(root / "template" / "base.py", "_load_image", load_image_ns, cls="Template")
    template.load_image = vision_utils.load_image

    def route(name: str, dataset_arg: str, cwd: Path, *, exact: bool) -> bool:
        """One way of loading; ``exact``: the images must reach the template as the files' bytes."""
        tally = Tally(name, lines, data)
        same = {True: 0, False: 0}
        pixels: dict[str, list[float]] = collections.defaultdict(list)
        with _cwd(cwd):
            train, _ = loader.load_dataset(dataset_arg, load_from_cache_file=False)
            for k, row in enumerate(train):
                messages = row["messages"]
                roles = [m["role"] for m in messages]
                if roles != ["system", "user", "assistant"]:
                    tally.problems.append(f"line {k + 1}: roles {roles}")
                    continue
                # The template's two modes: load_images=False passes a path on where one exists (else the
                # bytes, opened); True opens every image.
                lazy = [load_image(image, False) for image in row["images"]]
                unopenable = [x for x in lazy if not isinstance(x, Image.Image) and not os.path.isfile(x)]
                if unopenable:
                    tally.problems.append(f"line {k + 1}: load_images=False gives {unopenable[0]!r}")
                opened = [load_image(image, True) for image in row["images"]]
                tally.row(k, messages[0]["content"], messages[1]["content"], messages[2]["content"], opened)
                for image, rel in zip(row["images"], lines[k]["images"], strict=False):  # what the template reads
                    given = image["bytes"] if image.get("bytes") else (data / image["path"]).read_bytes()
                    same[given == (data / rel).read_bytes()] += 1
                    if given != (data / rel).read_bytes():
                        with Image.open(io.BytesIO(given)) as a, Image.open(data / rel) as b:
                            diff = np.abs(np.asarray(a.convert("RGB"), float) - np.asarray(b.convert("RGB"), float))
                            pixels[f"{b.format} as {a.format}"].append(float(diff.max()))
        if exact and same[False]:
            tally.problems.append(f"{same[False]} images reach the template not as their files' bytes")
        ok = tally.report()
        print(f"    the bytes the template reads are the files' bytes for {same[True]} of {sum(same.values())} images")
        for kind, worst in sorted(pixels.items()):
            print(f"    re-encoded {kind}: {len(worst)}, pixels equal in {sum(w == 0 for w in worst)}, "
                  f"largest difference {max(worst):.0f} of 255")
        return ok

    ok = route("ms-swift, cd DIR && --dataset export.jsonl", "export.jsonl", data, exact=True)
    ok &= route("ms-swift, --dataset DIR:raw (Parquet, images embedded, not decoded)", f"{data}:raw", work, exact=True)
    ok &= route("ms-swift, --dataset DIR (Parquet, the Image feature)", str(data), work, exact=False)
    # The same JSONL from another directory and no ROOT_IMAGE_DIR: ms-swift opens relative paths from the
    # working directory, so this is expected to fail (what the documented `cd DIR` is for).
    with _cwd(work):
        train, _ = loader.load_dataset(str(data / "export.jsonl"), load_from_cache_file=False)
        try:
            load_image(train[0]["images"][0], True)
            print("  ms-swift, --dataset DIR/export.jsonl from elsewhere: the first image opened (unexpected)")
        except (OSError, ValueError) as exc:
            print(f"  ms-swift, --dataset DIR/export.jsonl from elsewhere, no ROOT_IMAGE_DIR: the first image does not "
                  f"open ({type(exc).__name__}), as expected")
    return ok


# ----- datasets ---------------------------------------------------------------------------------------
def hf_datasets(data: Path, lines: list[dict[str, Any]], work: Path) -> bool:
    with _cwd(work):
        ds = datasets.load_dataset(str(data), split="train", cache_dir=str(work / "hf-cache"))
    tally = Tally(f"datasets {datasets.__version__}, load_dataset(DIR, split='train')", lines, data)
    for k, row in enumerate(ds):
        tally.row(k, *(m["content"] for m in row["messages"]), row["images"])
    return tally.report()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dir", type=Path, help="a dataset directory (the --out of agos dataset build)")
    parser.add_argument("--llamafactory", type=Path, help="hiyouga/LLaMA-Factory: a checkout or a git directory")
    parser.add_argument("--ms-swift", type=Path, help="modelscope/ms-swift: a checkout or a git directory")
    args = parser.parse_args()
    ok = True
    with tempfile.TemporaryDirectory(prefix="agos-loaders-") as tmp:
        work = Path(tmp)
        data = work / f"moved-{args.dir.resolve().name}"
        shutil.copytree(args.dir, data, copy_function=os.link, ignore=shutil.ignore_patterns("dataset-*", ".partial"))
        lines = [json.loads(x) for x in (data / "export.jsonl").read_text().splitlines()]
        print(f"{args.dir} copied to {data} (hard links; the run folder left out): {len(lines)} lines, "
              f"{sum(len(x['images']) for x in lines)} images; working directory {work}")
        ok &= hf_datasets(data, lines, work)
        if args.llamafactory:
            ok &= llamafactory(args.llamafactory, data, lines, work)
        if args.ms_swift:
            ok &= ms_swift(args.ms_swift, data, lines, work)
    print("all routes loaded every line and image" if ok else textwrap.fill("some route failed (above)"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
