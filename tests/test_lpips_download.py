"""Classic LPIPS's weight files: downloaded into the torch hub cache once where the network
allows, read from it without a download when they are there, and offline one line and ST-LPIPS
at once (difftex.evaluation.perceptual). No test here uses the network: the probe and the
download are replaced, and tests/conftest.py sets DIFFTEX_OFFLINE for every other test."""

from __future__ import annotations

import shutil
import threading

import numpy as np
import pytest

from difftex.evaluation import metrics, perceptual

from tests import piq_weights as W

HEADER = ("LPIPS (piq 0.8.0, VGG16: torchvision ImageNet weights vgg16-397923af.pth + piq linear weights "
          "lpips_weights.pt)")


def pair():
    rng = np.random.default_rng(0)
    a = rng.random((48, 48, 3))
    return a, np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1)


def stlpips_available():
    return perceptual.lpips_source("stlpips")[0] is not None


@pytest.fixture(scope="module")
def stand_ins(tmp_path_factory):
    """Random stand-ins for the two files (tests/piq_weights.py), in a folder of their own."""
    return W.write_piq_weights(tmp_path_factory.mktemp("stand_ins"))


@pytest.fixture
def online(monkeypatch, tmp_path):
    """Downloads allowed (DIFFTEX_OFFLINE unset), an empty hub cache, and the probe and the
    download recorded; each test says what they do. The download's outcome is per process, so
    it is forgotten before and after."""
    monkeypatch.delenv(perceptual.OFFLINE_ENV, raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    calls: dict[str, list] = {"probe": [], "download": []}

    def no_probe(url, timeout=perceptual.PROBE_TIMEOUT_S):
        calls["probe"].append(url)
        raise AssertionError("probed the network")

    def no_download(url, dst, hash_prefix):
        calls["download"].append(url)
        raise AssertionError("downloaded")

    monkeypatch.setattr(perceptual, "probe", no_probe)
    monkeypatch.setattr(perceptual, "download", no_download)
    perceptual.fetch_hub_weights.cache_clear()
    yield calls
    perceptual.fetch_hub_weights.cache_clear()


def warnings_of(caplog):
    return [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]


@pytest.mark.skipif(not stlpips_available(), reason="stlpips-pytorch does not import here")
def test_offline_says_so_in_one_line_and_reports_stlpips(online, monkeypatch, tmp_path, caplog):
    def unreachable(url, timeout=perceptual.PROBE_TIMEOUT_S):
        online["probe"].append(url)
        return "github.com: [Errno -2] Name or service not known"

    monkeypatch.setattr(perceptual, "probe", unreachable)
    a, b = pair()
    for _ in range(2):  # the failure is remembered: probed once per process, not per image
        value, label = metrics.lpips(a, b, variant="auto")
        assert value > 0 and label.startswith("ST-LPIPS (stlpips-pytorch")
    assert online["probe"] == [perceptual.weight_urls()["lpips"]] and online["download"] == []
    notes = warnings_of(caplog)
    assert len(notes) == 2 and notes[0] == notes[1] and "\n" not in notes[0], notes  # one line per call
    assert notes[0].startswith("LPIPS (auto): classic LPIPS (piq) needs lpips_weights.pt and vgg16-397923af.pth in ")
    assert "not downloaded, no network: github.com: [Errno -2] Name or service not known" in notes[0]
    assert "reporting ST-LPIPS instead" in notes[0]
    assert not (tmp_path / "torch").exists()  # nothing written to the hub cache


@pytest.mark.skipif(not stlpips_available(), reason="stlpips-pytorch does not import here")
def test_a_failed_download_falls_back_in_one_line(online, monkeypatch, tmp_path, caplog):
    monkeypatch.setattr(perceptual, "probe", lambda url, timeout=0: None)  # the servers answer ...

    def broken(url, dst, hash_prefix):  # ... but the transfer fails
        online["download"].append(url)
        raise OSError("connection reset by peer")

    monkeypatch.setattr(perceptual, "download", broken)
    value, label = metrics.lpips(*pair(), variant="auto")
    assert value > 0 and label.startswith("ST-LPIPS")
    assert len(online["download"]) == 1
    notes = warnings_of(caplog)
    assert len(notes) == 2, notes  # the download's notice, then the fallback's line
    assert notes[0].startswith("LPIPS: downloading piq's classic LPIPS weights (lpips_weights.pt and "
                               "vgg16-397923af.pth, 528 MB) into ")
    assert ("(missing: lpips_weights.pt, vgg16-397923af.pth; download failed: OSError: connection reset by peer); "
            "reporting ST-LPIPS instead") in notes[1]
    folder = tmp_path / "torch" / "hub" / "checkpoints"
    assert not [p for p in folder.iterdir() if p.suffix in (".pt", ".pth", ".partial")]


def test_weights_in_the_hub_cache_are_used_without_a_download(online, stand_ins, tmp_path, monkeypatch, caplog):
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    shutil.copytree(stand_ins, hub)
    value, label = metrics.lpips(*pair(), variant="auto")
    assert label == HEADER and value > 0
    assert online == {"probe": [], "download": []} and not warnings_of(caplog)


def test_missing_weights_are_downloaded_once_into_the_hub_cache(online, stand_ins, tmp_path, monkeypatch, caplog):
    def answers(url, timeout=perceptual.PROBE_TIMEOUT_S):
        online["probe"].append(url)
        return None

    def fetch(url, dst, hash_prefix):  # what torch.hub would write, from the stand-ins
        online["download"].append((url, dst.name, hash_prefix))
        shutil.copyfile(stand_ins / dst.name, dst)

    monkeypatch.setattr(perceptual, "probe", answers)
    monkeypatch.setattr(perceptual, "download", fetch)
    urls = perceptual.weight_urls()
    for _ in range(2):
        value, label = metrics.lpips(*pair(), variant="auto")
        assert label == HEADER and value > 0
    assert online["download"] == [(urls["lpips"], W.LPIPS_FILE, None), (urls["vgg16"], W.VGG16_FILE, "397923af")]
    assert online["probe"] == [urls["lpips"], urls["vgg16"]]  # once, before anything is written
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    assert (hub / W.LPIPS_FILE).is_file() and (hub / W.VGG16_FILE).is_file()
    notes = warnings_of(caplog)
    assert len(notes) == 1 and notes[0] == (
        "LPIPS: downloading piq's classic LPIPS weights (lpips_weights.pt and vgg16-397923af.pth, 528 MB) "
        f"into {hub}, once"
    )


def test_only_the_missing_file_is_downloaded(online, stand_ins, tmp_path, monkeypatch, caplog):
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    shutil.copyfile(stand_ins / W.VGG16_FILE, hub / W.VGG16_FILE)
    monkeypatch.setattr(perceptual, "probe", lambda url, timeout=0: None)
    monkeypatch.setattr(perceptual, "download",
                        lambda url, dst, hash_prefix: shutil.copyfile(stand_ins / dst.name, dst))
    assert perceptual.lpips_source("lpips")[1] == HEADER
    assert warnings_of(caplog) == [
        f"LPIPS: downloading piq's classic LPIPS weights (lpips_weights.pt) into {hub}, once"
    ]


def test_no_download_when_offline_is_set_or_for_a_configured_folder(online, tmp_path, monkeypatch):
    monkeypatch.setenv(perceptual.OFFLINE_ENV, "1")
    assert perceptual.classic_lpips_missing().endswith(
        "(missing: lpips_weights.pt, vgg16-397923af.pth; not downloaded: DIFFTEX_OFFLINE is set)"
    )
    monkeypatch.setenv(perceptual.OFFLINE_ENV, "0")  # 0: downloads allowed; a configured folder is only read
    assert perceptual.classic_lpips_missing(tmp_path / "weights").endswith(
        "(missing: lpips_weights.pt, vgg16-397923af.pth; a configured folder is never downloaded into)"
    )
    assert online == {"probe": [], "download": []}


def test_the_probe_gives_up_on_a_server_that_does_not_answer(monkeypatch):
    """A name lookup or connection that hangs is given up on after the probe's timeout (urllib's
    own timeout does not bound the lookup); a refused one is reported as it comes."""
    import urllib.request

    never = threading.Event()

    def hangs(request, timeout=None):
        never.wait(30)  # the probe's daemon thread is left waiting; the test does not wait for it
        raise OSError("late")

    monkeypatch.setattr(urllib.request, "urlopen", hangs)
    assert perceptual.probe("https://github.com/x.pt", timeout=0.2) == "github.com did not answer within 0.2 s"
    never.set()

    def refuses(request, timeout=None):
        raise urllib.error.URLError(OSError(-2, "Name or service not known"))

    monkeypatch.setattr(urllib.request, "urlopen", refuses)
    assert perceptual.probe("https://download.pytorch.org/models/x.pth") == (
        "download.pytorch.org: [Errno -2] Name or service not known"
    )
