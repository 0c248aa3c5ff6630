"""crater_synth.fetch + data_manifest.products: registry, verification, resumable atomic downloads."""

from __future__ import annotations

import hashlib
import http.server
import json
import threading

import pytest
from click.testing import CliRunner

from crater_synth import fetch
from crater_synth.cli import main
from data_manifest import products
from data_manifest.products import ChecksumError, ProductError

PAYLOAD = bytes(range(256)) * 1000  # 256 kB
SHA = hashlib.sha256(PAYLOAD).hexdigest()


class _Handler(http.server.BaseHTTPRequestHandler):
    """Serves ``server.files`` with Range support; records the Range headers it saw."""

    def do_GET(self):  # noqa: N802 - http.server API
        srv = self.server
        srv.ranges.append(self.headers.get("Range"))
        data = srv.files.get(self.path.lstrip("/"))
        if data is None:
            self.send_error(404)
            return
        start = 0
        rng = self.headers.get("Range")
        if rng and srv.honour_range:
            start = int(rng.split("=")[1].split("-")[0])
            if start >= len(data):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(data)}")
                self.end_headers()
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        else:
            self.send_response(200)
        body = data[start:]
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if srv.drop_after is not None:  # simulate a connection dropped mid-transfer, once
            cut, srv.drop_after = srv.drop_after, None
            self.wfile.write(body[:cut])
            self.wfile.flush()
            self.connection.close()
            return
        self.wfile.write(body)

    def log_message(self, *args):  # keep test output clean
        pass


@pytest.fixture()
def server():
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    srv.files, srv.ranges, srv.honour_range, srv.drop_after = {"pds/a.bin": PAYLOAD}, [], True, None
    thread = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def product(sha=SHA, size=len(PAYLOAD), path="pds/a.bin"):
    return {
        "id": "test_product",
        "source": "download",
        "archive": "mirror",
        "open": "a.bin",
        "files": [{"name": "a.bin", "path": path, "size_bytes": size, "sha256": sha}],
    }


def settings(srv, **kw):
    return {
        "base_url": f"http://127.0.0.1:{srv.server_address[1]}",
        "timeout_s": 10.0,
        "retries": 2,
        "backoff_s": 0.0,
        **kw,
    }


def test_good_file_downloads_and_verifies(server, tmp_path):
    rep = fetch.fetch_product(product(), tmp_path, settings(server), archives={"mirror": {}})
    dest = tmp_path / "products" / "a.bin"
    assert rep["status"] == "downloaded" and dest.read_bytes() == PAYLOAD
    assert not (tmp_path / "products" / "a.bin.part").exists()
    again = fetch.fetch_product(product(), tmp_path, settings(server), archives={"mirror": {}})
    assert again["status"] == "present" and len(server.ranges) == 1  # no second download


def test_bad_checksum_leaves_nothing(server, tmp_path):
    with pytest.raises(ChecksumError, match="sha256 mismatch") as info:
        fetch.fetch_product(product(sha="0" * 64), tmp_path, settings(server), archives={"mirror": {}})
    assert "\n" not in str(info.value) and "nothing kept" in str(info.value)
    assert not list((tmp_path / "products").iterdir())


def test_wrong_size_leaves_nothing(server, tmp_path):
    with pytest.raises(ChecksumError, match="size"):
        fetch.fetch_product(product(size=123), tmp_path, settings(server), archives={"mirror": {}})
    assert not list((tmp_path / "products").iterdir())


def test_resume_from_partial_part_file(server, tmp_path):
    out = tmp_path / "products"
    out.mkdir()
    (out / "a.bin.part").write_bytes(PAYLOAD[:100_000])
    rep = fetch.fetch_product(product(), tmp_path, settings(server), archives={"mirror": {}})
    assert rep["status"] == "downloaded" and (out / "a.bin").read_bytes() == PAYLOAD
    assert server.ranges == ["bytes=100000-"]
    assert not (out / "a.bin.part").exists()


def test_resume_after_dropped_connection(server, tmp_path):
    server.drop_after = 70_000
    fetch.fetch_product(product(), tmp_path, settings(server, chunk_bytes=4096), archives={"mirror": {}})
    assert (tmp_path / "products" / "a.bin").read_bytes() == PAYLOAD
    assert server.ranges == [None, "bytes=70000-"]  # the retry resumed where the connection dropped


def test_server_ignoring_range_restarts_cleanly(server, tmp_path):
    server.honour_range = False
    out = tmp_path / "products"
    out.mkdir()
    (out / "a.bin.part").write_bytes(PAYLOAD[:5000])
    fetch.fetch_product(product(), tmp_path, settings(server), archives={"mirror": {}})
    assert (out / "a.bin").read_bytes() == PAYLOAD


def test_missing_remote_file_is_one_error(server, tmp_path):
    with pytest.raises(fetch.FetchError, match="404"):
        fetch.fetch_product(product(path="pds/missing.bin"), tmp_path, settings(server), archives={"mirror": {}})


def test_archive_without_url_needs_a_mirror(tmp_path):
    with pytest.raises(fetch.FetchError, match="fetch.base_url"):
        fetch.fetch_product(product(), tmp_path, {"base_url": None}, archives={"mirror": {"name": "m"}})


def test_registry_is_consistent():
    reg = products.load_products()
    for pid in (
        "lola_ldem256_south",
        "lroc_wac_south",
        "lola_ldem_875s_20m",
        "lola_ldem_85s_40m",
        "lola_ldem_80s_80m",
        "lroc_m101457600mc",
        "lroc_m139810920mc",
        "selene_tc_tc1w2b0_01_00582s883e2719",
        "selene_hdtv_shackleton",
    ):
        assert pid in reg and reg[pid].get("licence"), pid
    assert reg["lola_ldem256_south"]["sha256"].startswith("12c33e28")
    with pytest.raises(ProductError, match="unknown data product"):
        products.get_product("nope")


def test_embedded_products_resolve_and_verify(tmp_path):
    p = products.resolve_product("lola_ldem256_south", tmp_path)
    assert p.name == "lola_dem_south.tif"
    assert products.verify_sha256(p, products.get_product("lola_ldem256_south")["sha256"])
    w = products.resolve_product("lroc_wac_south", tmp_path)
    with pytest.raises(ChecksumError, match="sha256 mismatch"):
        products.verify_sha256(w, "f" * 64)


def test_downloadable_product_missing_locally(tmp_path):
    with pytest.raises(products.ProductMissingError, match="fetch-data lola_ldem_875s_20m"):
        products.resolve_product("lola_ldem_875s_20m", tmp_path)


def test_cli_embedded_and_mirror(server, tmp_path, monkeypatch):
    runner = CliRunner()
    res = runner.invoke(main, ["fetch-data", "lola_ldem256_south", f"data_dir={tmp_path}"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["status"] == "embedded-verified"

    res = runner.invoke(main, ["fetch-data", "no_such_product", f"data_dir={tmp_path}"])
    assert res.exit_code == 2 and res.stderr.startswith("error: unknown data product")

    reg = {**products.load_products(), "test_product": {k: v for k, v in product().items() if k != "id"}}
    monkeypatch.setattr(products, "load_products", lambda *a, **k: reg)
    monkeypatch.setattr(fetch, "load_products", lambda *a, **k: reg)  # fetch imports it at its top
    monkeypatch.setattr(products, "load_archives", lambda *a, **k: {"mirror": {"name": "m", "base_url": None}})
    res = runner.invoke(
        main,
        [
            "fetch-data",
            "test_product",
            f"data_dir={tmp_path}",
            f"fetch.base_url={settings(server)['base_url']}",
            "fetch.backoff_s=0",
        ],
    )
    assert res.exit_code == 0, res.output
    row = json.loads(res.stdout)
    assert row["status"] == "downloaded" and (tmp_path / "products" / "a.bin").read_bytes() == PAYLOAD

    res = runner.invoke(main, ["fetch-data", f"data_dir={tmp_path}"])  # status of everything, no download
    assert res.exit_code == 0
    status = {r["product"]: r["status"] for r in map(json.loads, res.stdout.splitlines())}
    assert status["test_product"] == "present" and status["lola_ldem_875s_20m"] == "missing"


def test_trust_on_first_use_pins_an_unpinned_file(server, tmp_path, monkeypatch):
    """A file without a registry sha256 is pinned at its first fetch and checked at every later use."""
    unpinned = product(sha=None, size=None)
    rep = fetch.fetch_product(unpinned, tmp_path, settings(server), archives={"mirror": {}})
    assert rep["files"][0]["pinned"].startswith("pinned now") and "trust on first use" in rep["note"]
    pins = products.load_pins(tmp_path)
    assert pins["test_product/a.bin"]["sha256"] == SHA and pins["test_product/a.bin"]["bytes"] == len(PAYLOAD)
    again = fetch.fetch_product(unpinned, tmp_path, settings(server), archives={"mirror": {}})
    assert again["files"][0]["pinned"] == "first-fetch pin" and "note" not in again

    reg = {"test_product": {k: v for k, v in unpinned.items() if k != "id"}}
    monkeypatch.setattr(products, "load_products", lambda *a, **k: reg)
    monkeypatch.setattr(fetch, "load_products", lambda *a, **k: reg)  # fetch imports it at its top
    assert products.resolve_product("test_product", tmp_path).read_bytes() == PAYLOAD
    # The archive now serves other bytes: a fresh fetch is refused against the pin, nothing kept.
    (tmp_path / "products" / "a.bin").unlink()
    server.files["pds/a.bin"] = PAYLOAD[::-1]
    with pytest.raises(ChecksumError, match="sha256 mismatch"):
        fetch.fetch_product(unpinned, tmp_path, settings(server), archives={"mirror": {}})
    assert not (tmp_path / "products" / "a.bin").exists()
    # A local file changed after pinning is refused when used.
    (tmp_path / "products" / "a.bin").write_bytes(b"tampered")
    with pytest.raises(ChecksumError, match="first-fetch pin"):
        products.resolve_product("test_product", tmp_path)


def test_present_but_never_pinned_file_is_not_trusted_silently(tmp_path, monkeypatch):
    reg = {"test_product": {k: v for k, v in product(sha=None).items() if k != "id"}}
    monkeypatch.setattr(products, "load_products", lambda *a, **k: reg)
    monkeypatch.setattr(fetch, "load_products", lambda *a, **k: reg)  # fetch imports it at its top
    (tmp_path / "products").mkdir()
    (tmp_path / "products" / "a.bin").write_bytes(PAYLOAD)
    with pytest.raises(products.ProductMissingError, match="no pinned sha256.*fetch-data test_product"):
        products.resolve_product("test_product", tmp_path)


def test_alternative_archive_path_after_a_404(server, tmp_path):
    p = product()
    p["files"][0] = dict(p["files"][0], path="pds/2009186/a.bin", alt_paths=["pds/a.bin"])
    rep = fetch.fetch_product(p, tmp_path, settings(server), archives={"mirror": {}})
    assert rep["files"][0]["url"].endswith("/pds/a.bin") and (tmp_path / "products" / "a.bin").read_bytes() == PAYLOAD


def test_gzip_file_is_unpacked_beside_the_pinned_archive_file(server, tmp_path):
    import gzip

    gz = gzip.compress(PAYLOAD)
    server.files["pds/a.bin.gz"] = gz
    p = product(sha=hashlib.sha256(gz).hexdigest(), size=len(gz), path="pds/a.bin.gz")
    p["files"][0] = dict(p["files"][0], name="a.bin.gz", unpack="gzip")
    fetch.fetch_product(p, tmp_path, settings(server), archives={"mirror": {}})
    assert (tmp_path / "products" / "a.bin").read_bytes() == PAYLOAD
    assert (tmp_path / "products" / "a.bin.gz").read_bytes() == gz
    assert not [f for f in (tmp_path / "products").iterdir() if f.name.endswith(".tmp")]


def test_paper_frames_have_archive_locations():
    reg, arch = products.load_products(), products.load_archives()
    for pid in ("lroc_m101457600mc", "lroc_m139810920mc", "selene_tc_tc1w2b0_01_00582s883e2719"):
        p = reg[pid]
        assert arch[p["archive"]]["base_url"].startswith("https://"), pid
        assert p["files"] and all(f["sha256"] is None for f in p["files"])  # pinned at the first fetch
    assert reg["lroc_m101457600mc"]["files"][0]["path"].startswith("LRO-L-LROC-3-CDR-V1.0/LROLRC_1001/DATA/")
    assert reg["selene_tc_tc1w2b0_01_00582s883e2719"]["files"][0]["path"].startswith("sln-l-tc-3-w-level2b0-v1.0/")
