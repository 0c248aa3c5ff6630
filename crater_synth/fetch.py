"""``crater-synth fetch-data``: download registered data products (data_manifest/products.yaml).

Each file goes to ``<data_dir>/products/<name>`` through ``<name>.part``: an interrupted download
resumes with an HTTP ``Range`` request, the finished file is checked against its pinned size and
sha256, and only then renamed into place (atomic). A mismatch is one error and leaves neither the
file nor its ``.part``. Embedded products are only verified. Standard library only (urllib).

URL of a file: ``<fetch.base_url>/<path>`` when ``fetch.base_url`` is set (a mirror keeping the
registry's layout), else ``<archive base_url>/<path>`` from the registry (docs/data.md).
"""

from __future__ import annotations

import gzip
import http.client
import json
import os
import shutil
import socket
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import click
from omegaconf import OmegaConf

from crater_core.errors import ContractError
from crater_core.schema import sha256_file
from crater_synth.cli_common import user_errors
from crater_synth.config import compose
from crater_synth.errors import UserError
from data_manifest.products import (
    ChecksumError,
    ProductError,
    expected_sha256,
    get_product,
    load_archives,
    load_pins,
    load_products,
    local_name,
    pins_path,
    products_dir,
    record_pin,
    resolve_product,
)

# Used when the composed config has no ``fetch`` group (configs/fetch/default.yaml holds the same).
FETCH_DEFAULTS = {"base_url": None, "timeout_s": 60.0, "retries": 3, "chunk_bytes": 1 << 20, "backoff_s": 1.0}
USER_AGENT = "crater-synth-fetch/0.1 (python-urllib)"
# HTTP statuses that will not change on retry.
_FATAL_HTTP = {400, 401, 403, 404, 405, 410, 451}


class FetchError(UserError):
    """A product could not be downloaded (network, missing URL, bad registry entry). ``http_status``:
    the server's final HTTP status, when there was one."""

    http_status: int | None = None


# --------------------------------------------------------------------------------------------
# Settings and URLs
# --------------------------------------------------------------------------------------------
def fetch_settings(cfg) -> dict:
    """``fetch.*`` with defaults, validated."""
    node = cfg.get("fetch") if cfg is not None else None
    if node is not None and not isinstance(node, dict):
        raw = OmegaConf.to_container(node, resolve=True)
    else:
        raw = node or {}
    s = {**FETCH_DEFAULTS, **{k: v for k, v in dict(raw).items() if v is not None or k == "base_url"}}
    try:
        s["timeout_s"] = float(s["timeout_s"])
        s["retries"] = int(s["retries"])
        s["chunk_bytes"] = int(s["chunk_bytes"])
        s["backoff_s"] = float(s["backoff_s"])
    except (TypeError, ValueError) as exc:
        raise FetchError(f"fetch.*: non-numeric value ({exc})") from None
    if s["timeout_s"] <= 0:
        raise FetchError(f"fetch.timeout_s={s['timeout_s']} must be > 0")
    if s["retries"] < 1:
        raise FetchError(f"fetch.retries={s['retries']} must be >= 1")
    if s["backoff_s"] < 0:
        raise FetchError(f"fetch.backoff_s={s['backoff_s']} must be >= 0")
    if s["chunk_bytes"] < 1024:
        raise FetchError(f"fetch.chunk_bytes={s['chunk_bytes']} must be >= 1024")
    if s["base_url"] is not None:
        s["base_url"] = str(s["base_url"]).strip() or None
        if s["base_url"] and not s["base_url"].startswith(("http://", "https://", "file://")):
            raise FetchError(f"fetch.base_url={s['base_url']!r} must start with http://, https:// or file://")
    return s


def file_url(product: dict, entry: dict, base_url: str | None, archives: dict, path: str | None = None) -> str:
    """Download URL of one file of a product (``path``: one of its ``alt_paths`` instead of ``path``)."""
    path = path or entry["path"]
    if base_url:
        return f"{base_url.rstrip('/')}/{path.lstrip('/')}"
    arch = archives.get(product.get("archive"), {})
    if not arch.get("base_url"):
        raise FetchError(
            f"data product {product['id']!r}: archive {product.get('archive')!r} ({arch.get('name', '?')}) has no "
            f"URL known offline; set fetch.base_url=<mirror> serving {path}"
        )
    return f"{arch['base_url'].rstrip('/')}/{path.lstrip('/')}"


# --------------------------------------------------------------------------------------------
# Download of one file
# --------------------------------------------------------------------------------------------
def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _check(path: Path, expected_sha: str | None, expected_size: int | None, what: str) -> tuple[str, int]:
    """(sha256, size) of ``path``; ChecksumError on a size or digest mismatch."""
    size = path.stat().st_size
    if expected_size is not None and size != int(expected_size):
        raise ChecksumError(f"{what}: size {size} bytes != pinned {int(expected_size)}")
    digest = sha256_file(path)
    if expected_sha is not None and digest != str(expected_sha).lower():
        raise ChecksumError(f"{what}: sha256 mismatch (expected {expected_sha}, got {digest})")
    return digest, size


def _download_into(part: Path, url: str, timeout_s: float, chunk: int) -> None:
    """Append the rest of ``url`` to ``part`` (Range resume); restart if the server ignores Range."""
    offset = part.stat().st_size if part.exists() else 0
    headers = {"User-Agent": USER_AGENT}
    if offset:
        headers["Range"] = f"bytes={offset}-"
    req = urllib.request.Request(url, headers=headers)
    with urllib.request.urlopen(req, timeout=timeout_s) as resp:
        status = getattr(resp, "status", 200)
        start = 0
        if offset and status == 206:
            crange = resp.headers.get("Content-Range", "")
            if not crange.startswith(f"bytes {offset}-"):
                raise urllib.error.URLError(f"server answered Content-Range {crange!r} to a resume from {offset}")
            start = offset
        length = resp.headers.get("Content-Length")
        expected_end = start + int(length) if length and length.isdigit() else None
        with open(part, "ab" if start else "wb") as fh:
            while block := resp.read(chunk):
                fh.write(block)
            fh.flush()
            os.fsync(fh.fileno())
            end = fh.tell()
    if expected_end is not None and end < expected_end:
        # The connection closed early; the caller retries and resumes from here.
        raise ConnectionError(f"connection closed after {end} of {expected_end} bytes")


def fetch_file(
    url: str,
    dest: Path,
    sha256: str | None,
    size_bytes: int | None,
    *,
    timeout_s: float = 60.0,
    retries: int = 3,
    chunk_bytes: int = 1 << 20,
    backoff_s: float = 1.0,
    what: str | None = None,
) -> dict:
    """Make ``dest`` a verified copy of ``url``; returns {status, sha256, bytes, path}.

    status: ``present`` (already there and valid) or ``downloaded``. Network errors keep the
    ``.part`` for a later resume; a checksum/size mismatch removes it and raises ChecksumError.
    """
    what = what or dest.name
    dest = Path(dest)
    if dest.exists():
        try:
            digest, size = _check(dest, sha256, size_bytes, f"{what}: existing file {dest}")
        except ChecksumError as exc:
            raise ChecksumError(f"{exc}; delete it to fetch again") from None
        return {"status": "present", "sha256": digest, "bytes": size, "path": str(dest), "pinned": sha256 is not None}
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    last: Exception | None = None
    for attempt in range(retries):
        if part.exists() and size_bytes is not None and part.stat().st_size >= int(size_bytes):
            break  # complete (or too long: the check below rejects it)
        try:
            _download_into(part, url, timeout_s, chunk_bytes)
            last = None
            break
        except urllib.error.HTTPError as exc:
            if exc.code == 416 and part.exists() and part.stat().st_size > 0:
                last = None  # nothing left to send: .part holds the whole file (checked below)
                break
            last = exc
            if exc.code in _FATAL_HTTP:
                break
        except (urllib.error.URLError, http.client.HTTPException, socket.timeout, TimeoutError, OSError) as exc:
            last = exc  # connection dropped, timeout, short read: retry, resuming from the .part
        if attempt + 1 < retries:
            time.sleep(min(backoff_s * 2.0**attempt, 30.0))
    if last is not None:
        reason = (
            f"HTTP {last.code} {last.reason}"
            if isinstance(last, urllib.error.HTTPError)
            else getattr(last, "reason", None) or last
        )
        kept = f"; partial data kept in {part} for resume" if part.exists() and part.stat().st_size else ""
        err = FetchError(f"cannot download {what} from {url}: {reason}{kept}")
        err.http_status = last.code if isinstance(last, urllib.error.HTTPError) else None
        raise err
    try:
        digest, size = _check(part, sha256, size_bytes, f"{what} downloaded from {url}")
    except ChecksumError as exc:
        part.unlink(missing_ok=True)
        raise ChecksumError(f"{exc}; nothing kept") from None
    os.replace(part, dest)
    _fsync_dir(dest.parent)
    return {"status": "downloaded", "sha256": digest, "bytes": size, "path": str(dest), "pinned": sha256 is not None}


# --------------------------------------------------------------------------------------------
# Products
# --------------------------------------------------------------------------------------------
def product_status(product: dict, data_dir: str | os.PathLike) -> dict:
    """Report a product's local state without downloading (embedded ones are verified)."""
    pid = product["id"]
    if product["source"] == "embedded":
        path = resolve_product(pid, data_dir)
        return {
            "product": pid,
            "source": "embedded",
            "status": "embedded-verified",
            "path": str(path),
            "sha256": product["sha256"],
        }

    pins = load_pins(data_dir)
    files = [
        {
            "name": f["name"],
            "present": (products_dir(data_dir) / f["name"]).is_file(),
            "sha256_from": expected_sha256(pid, f, pins)[1],
        }
        for f in product["files"]
    ]
    status = "not-pinned" if not files else "present" if all(f["present"] for f in files) else "missing"
    return {"product": pid, "source": "download", "status": status, "files": files}


def fetch_product(
    product: dict, data_dir: str | os.PathLike, settings: dict | None = None, archives: dict | None = None
) -> dict:
    """Verify an embedded product, or download every file of a downloadable one. Returns a report."""
    s = {**FETCH_DEFAULTS, **(settings or {})}
    pid = product["id"]
    if product["source"] == "embedded":
        path = resolve_product(pid, data_dir)
        return {
            "product": pid,
            "source": "embedded",
            "status": "embedded-verified",
            "path": str(path),
            "sha256": product["sha256"],
            "note": "already present (embedded, sha256 verified)",
        }
    if not product.get("files"):
        raise ProductError(f"data product {pid!r} has no pinned file in products.yaml (nothing to fetch)")
    archives = load_archives() if archives is None else archives
    out_dir = products_dir(data_dir)
    pins = load_pins(data_dir)
    reports = []
    for entry in product["files"]:
        expected, origin = expected_sha256(pid, entry, pins)
        paths = [entry["path"], *entry.get("alt_paths", [])]
        for k, path in enumerate(paths):
            url = file_url(product, entry, s["base_url"], archives, path)
            click.echo(f"fetch-data: {pid}: {entry['name']} <- {url}", err=True)
            try:
                rep = fetch_file(
                    url,
                    out_dir / entry["name"],
                    expected,
                    entry.get("size_bytes"),
                    timeout_s=s["timeout_s"],
                    retries=s["retries"],
                    chunk_bytes=s["chunk_bytes"],
                    backoff_s=s["backoff_s"],
                    what=f"data product {pid!r} file {entry['name']}",
                )
                break
            except FetchError as exc:
                # Not there: try the next candidate location (an archive directory not known exactly offline).
                if exc.http_status in (404, 410) and k + 1 < len(paths):
                    continue
                raise
        if expected is None:
            record_pin(data_dir, pid, entry["name"], rep["sha256"], rep["bytes"], url)
            origin = "pinned now (first fetch)"
        if entry.get("unpack") == "gzip":
            _gunzip(out_dir / entry["name"], out_dir / local_name(entry))
        reports.append({"name": entry["name"], "url": url, **rep, "pinned": origin})
    status = "downloaded" if any(r["status"] == "downloaded" for r in reports) else "present"
    out = {
        "product": pid,
        "source": "download",
        "status": status,
        "path": str(out_dir / product["open"]),
        "files": reports,
    }
    first = [r["name"] for r in reports if r["pinned"].startswith("pinned now")]
    if first:
        out["note"] = (
            f"trust on first use: {first} have no sha256 in products.yaml; their digests are now pinned in "
            f"{pins_path(data_dir)} and checked at every later use"
        )
    return out


def _gunzip(src: Path, dest: Path) -> None:
    """Decompress ``src`` into ``dest`` through a temporary file and a rename (kept if already there)."""
    if dest.is_file():
        return
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    try:
        with os.fdopen(fd, "wb") as out, gzip.open(src, "rb") as inp:
            shutil.copyfileobj(inp, out, 1 << 20)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, dest)
    except (OSError, EOFError) as exc:
        Path(tmp).unlink(missing_ok=True)
        raise FetchError(f"cannot decompress {src}: {exc}; nothing kept") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------
def _split_args(args) -> tuple[list[str], list[str]]:
    ids, overrides = [], []
    for a in args:
        (overrides if ("=" in a or a.startswith(("+", "~"))) else ids).append(a)
    return ids, overrides


@click.command("fetch-data")
@click.argument("args", nargs=-1, metavar="[PRODUCT_ID|all]... [OVERRIDES]...")
@user_errors
def fetch_data_command(args):
    """Fetch data products into <data_dir>/products/ (resumable, sha256-verified, atomic).

    With no product ID, report every registered product's local state without downloading.
    ``all`` fetches every product. Embedded products are verified, never downloaded.
    Example: ``crater-synth fetch-data lola_ldem_875s_20m fetch.base_url=http://mirror.local/pds``
    """
    ids, overrides = _split_args(args)
    cfg = compose(overrides)
    data_dir = Path(str(cfg.data_dir))
    settings = fetch_settings(cfg)
    if not ids:
        for pid in load_products():
            click.echo(json.dumps(product_status(get_product(pid), data_dir)))
        return
    fetch_all = "all" in ids
    if fetch_all:
        ids = list(load_products())
    products = [get_product(pid) for pid in dict.fromkeys(ids)]  # unknown IDs fail before any download
    if not fetch_all:
        for product in products:
            click.echo(json.dumps(fetch_product(product, data_dir, settings)))
        return
    # `all`: keep going past products that cannot be fetched here; one error line at the end.
    failed = []
    for product in products:
        try:
            click.echo(json.dumps(fetch_product(product, data_dir, settings)))
        except (UserError, ContractError) as exc:
            failed.append(product["id"])
            click.echo(json.dumps({"product": product["id"], "status": "error", "error": str(exc)}))
    if failed:
        raise FetchError(
            f"{len(failed)} of {len(products)} product(s) not fetched: {', '.join(failed)} (see their JSON lines)"
        )
