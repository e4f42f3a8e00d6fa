"""Learned metrics (LPIPS, SIFID, DreamSim) through the production loaders, with random weights made here.

Weight files are written by the tests in the torchvision / pytorch-fid / LPIPS key layouts with the real shapes,
so the loading code is exercised exactly as with the published files; no weights are downloaded.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy import linalg

from evaluation.metrics import compute_metrics, load_dreamsim, load_lpips, load_sifid_inception, lpips, sifid
from evaluation.metrics import metric_unavailable, weights_sha256
from evaluation.metrics import weights as weights_mod
from evaluation.metrics.lpips import LPIPS_CHANNELS, LPIPS_SCALE, LPIPS_SHIFT
from camo_base.errors import CamoError

ALEX_CONVS = {0: (64, 3, 11, 4, 2), 3: (192, 64, 5, 1, 2), 6: (384, 192, 3, 1, 1), 8: (256, 384, 3, 1, 1),
              10: (256, 256, 3, 1, 1)}
VGG_CONVS = dict(zip((0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28),
                     [(o, i, 3, 1, 1) for o, i in [(64, 3), (64, 64), (128, 64), (128, 128), (256, 128), (256, 256),
                                                  (256, 256), (512, 256), (512, 512), (512, 512), (512, 512),
                                                  (512, 512), (512, 512)]]))
INCEPTION_STEM = (("Conv2d_1a_3x3", 3, 32, 2, 0), ("Conv2d_2a_3x3", 32, 32, 1, 0), ("Conv2d_2b_3x3", 32, 64, 1, 1))


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _trunk_state_dict(convs: dict, seed: int = 0) -> dict[str, torch.Tensor]:
    """torchvision-format ``features.N.*`` weights (He init) plus a classifier key the loader must ignore."""
    g = _gen(seed)
    sd = {}
    for i, (o, c, k, _, _) in convs.items():
        sd[f"features.{i}.weight"] = torch.randn(o, c, k, k, generator=g) * (2.0 / (c * k * k)) ** 0.5
        sd[f"features.{i}.bias"] = 0.05 * torch.randn(o, generator=g)
    sd["classifier.6.bias"] = torch.zeros(10)
    return sd


def _lin_state_dict(net: str, seed: int = 1) -> dict[str, torch.Tensor]:
    g = _gen(seed)
    return {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) * 0.1
            for k, c in enumerate(LPIPS_CHANNELS[net])}


@pytest.fixture(scope="module")
def alex_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("lpips_alex")
    torch.save(_trunk_state_dict(ALEX_CONVS), d / "alexnet-test.pth")
    torch.save(_lin_state_dict("alex"), d / "alex.pth")
    return d / "alexnet-test.pth", d / "alex.pth"


def _lpips_reference(x: torch.Tensor, y: torch.Tensor, trunk: dict, lin: dict, convs: dict, pools: dict,
                     taps: tuple) -> torch.Tensor:
    """Plain functional LPIPS v0.1 on the raw state dicts (independent of the production modules)."""
    shift = torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1)
    scale = torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1)

    def feats(z):
        z = ((2 * z - 1) - shift) / scale
        out = []
        for i in range(max(taps) + 1):
            if i in convs:
                _, _, _, s, p = convs[i]
                z = F.conv2d(z, trunk[f"features.{i}.weight"], trunk[f"features.{i}.bias"], stride=s, padding=p)
            elif i in pools:
                z = F.max_pool2d(z, *pools[i])
            else:
                z = F.relu(z)
            if i in taps:
                out.append(z)
        return out

    total = torch.zeros(x.shape[0])
    for k, (a, b) in enumerate(zip(feats(x), feats(y))):
        a = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        b = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        total += F.conv2d((a - b) ** 2, lin[f"lin{k}.model.1.weight"]).mean(dim=(1, 2, 3))
    return total


def _images(n: int, h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.rand(n, 3, h, w, generator=_gen(seed))
    y = (x + 0.15 * torch.randn(n, 3, h, w, generator=_gen(seed + 1))).clamp(0, 1)
    return x, y


# ---------------------------------------------------------------- LPIPS


def test_lpips_alex_from_torchvision_format_weights(alex_files):
    trunk, lin = alex_files
    model = load_lpips("alex", trunk, lin)
    x, y = _images(2, 64, 72, 0)
    got = lpips(x, y, model)
    ref = _lpips_reference(x, y, torch.load(trunk), torch.load(lin), ALEX_CONVS, {2: (3, 2), 5: (3, 2)},
                           (1, 4, 7, 9, 11))
    assert got.shape == (2,) and torch.allclose(got, ref, rtol=1e-5, atol=1e-7)
    assert (got > 0).all()
    assert torch.equal(lpips(x, x, model), torch.zeros(2))  # identical images -> exactly 0
    assert torch.allclose(lpips(y, x, model), got, rtol=1e-5)
    assert model.weights_sha256 == {"trunk": weights_sha256(trunk), "lin": weights_sha256(lin)}
    assert load_lpips("alex", trunk, lin) is model  # cached
    z = torch.zeros(1, 3, 32, 32)
    assert torch.isfinite(lpips(z, z, model)).all() and lpips(z, torch.ones_like(z), model).isfinite().all()


def test_lpips_vgg16_from_torchvision_format_weights(tmp_path):
    sd = _trunk_state_dict(VGG_CONVS, seed=3)
    torch.save(sd, tmp_path / "vgg16-test.pth")
    torch.save(_lin_state_dict("vgg", seed=4), tmp_path / "vgg.pth")
    model = load_lpips("vgg", tmp_path / "vgg16-test.pth", tmp_path / "vgg.pth")
    x, y = _images(1, 32, 32, 5)
    pools = {i: (2, 2) for i in (4, 9, 16, 23)}
    ref = _lpips_reference(x, y, sd, _lin_state_dict("vgg", seed=4), VGG_CONVS, pools, (3, 8, 15, 22, 29))
    assert torch.allclose(lpips(x, y, model), ref, rtol=1e-5, atol=1e-7)
    assert lpips(x, x, model).item() == 0.0


def test_lpips_finds_weights_in_torch_home_and_wheels(tmp_path, monkeypatch, alex_files):
    trunk, lin = alex_files
    ckpt = tmp_path / "hub" / "checkpoints"
    ckpt.mkdir(parents=True)
    (ckpt / "alexnet-owt-7be5be79.pth").write_bytes(trunk.read_bytes())
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    wheel = tmp_path / "site" / "torchmetrics" / "functional" / "image" / "lpips_models"
    wheel.mkdir(parents=True)
    (wheel / "alex.pth").write_bytes(lin.read_bytes())
    monkeypatch.setattr(weights_mod, "lpips_lin_candidates", lambda net: [wheel / f"{net}.pth"])
    model = load_lpips("alex")
    assert model.weight_paths == {"trunk": str(ckpt / "alexnet-owt-7be5be79.pth"), "lin": str(wheel / "alex.pth")}
    assert metric_unavailable("lpips") is None


def test_lpips_in_compute_metrics_records_weights(alex_files):
    trunk, lin = alex_files
    x, y = _images(1, 40, 48, 12)
    row = compute_metrics(x, y, ["lpips", "psnr"], {"lpips_trunk": trunk, "lpips_lin": lin})
    assert row["lpips"] == pytest.approx(lpips(x, y, load_lpips("alex", trunk, lin)).item())
    assert row["lpips_variant"] == "alex-v0.1"
    assert row["lpips_weights_sha256"] == f"trunk:{weights_sha256(trunk)};lin:{weights_sha256(lin)}"


def test_official_lpips_linear_layers_when_a_wheel_ships_them(alex_files):
    found = [p for p in weights_mod.lpips_lin_candidates("alex") if p.is_file()]
    if not found:
        pytest.skip("neither the lpips nor the torchmetrics wheel is installed")
    assert weights_sha256(found[0]) == weights_mod.LPIPS_LIN_V01_SHA256["alex"]
    model = load_lpips("alex", alex_files[0])
    assert model.weight_paths["lin"] == str(found[0])


def test_lpips_missing_or_bad_weights_raise_camo_error(tmp_path, monkeypatch, alex_files):
    trunk, lin = alex_files
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty"))
    with pytest.raises(CamoError, match="never downloaded") as err:
        load_lpips("alex", None, lin)
    assert "camo data fetch data_manifests/lpips_weights.toml --dest" in str(err.value)  # names the fix
    monkeypatch.setattr(weights_mod, "lpips_lin_candidates", lambda net: [])
    with pytest.raises(CamoError, match="not installed.*camo data fetch"):
        load_lpips("alex", trunk, None)
    assert "never downloaded" in metric_unavailable("lpips")
    with pytest.raises(CamoError, match="not found"):
        load_lpips("alex", tmp_path / "nope.pth", lin)
    (tmp_path / "corrupt.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(CamoError, match="cannot read"):
        load_lpips("alex", tmp_path / "corrupt.pth", lin)
    wrong = _trunk_state_dict(ALEX_CONVS)
    wrong["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    torch.save(wrong, tmp_path / "wrong.pth")
    with pytest.raises(CamoError, match="features.3.weight.*expected"):
        load_lpips("alex", tmp_path / "wrong.pth", lin)
    with pytest.raises(CamoError, match="lack key"):
        load_lpips("alex", trunk, trunk)  # a trunk file given as the linear layers
    with pytest.raises(CamoError, match="'alex' or 'vgg'"):
        load_lpips("squeeze", trunk, lin)
    model = load_lpips("alex", trunk, lin)
    with pytest.raises(CamoError, match="at least 32"):
        lpips(torch.rand(1, 3, 24, 24), torch.rand(1, 3, 24, 24), model)


# ---------------------------------------------------------------- SIFID


def _inception_state_dict(seed: int = 7, prefix: str = "") -> dict[str, torch.Tensor]:
    g = _gen(seed)
    sd = {}
    for name, cin, cout, _, _ in INCEPTION_STEM:
        sd[f"{prefix}{name}.conv.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * (2.0 / (cin * 9)) ** 0.5
        sd[f"{prefix}{name}.bn.weight"] = 1 + 0.1 * torch.randn(cout, generator=g)
        sd[f"{prefix}{name}.bn.bias"] = 0.1 * torch.randn(cout, generator=g)
        sd[f"{prefix}{name}.bn.running_mean"] = 0.1 * torch.randn(cout, generator=g)
        sd[f"{prefix}{name}.bn.running_var"] = 0.5 + torch.rand(cout, generator=g)
        sd[f"{prefix}{name}.bn.num_batches_tracked"] = torch.tensor(0)
    sd[f"{prefix}fc.bias"] = torch.zeros(1000)  # rest of Inception3: ignored
    return sd


def _sifid_reference(x: np.ndarray, y: np.ndarray, sd: dict, maxpool: bool) -> float:
    """SinGAN's recipe written out: functional stem, np.cov over positions, scipy sqrtm Frechet."""

    def feats(img):
        z = 2 * torch.from_numpy(img).permute(2, 0, 1)[None].float() - 1
        for name, _, _, stride, pad in INCEPTION_STEM:
            z = F.conv2d(z, sd[f"{name}.conv.weight"], stride=stride, padding=pad)
            z = F.batch_norm(z, sd[f"{name}.bn.running_mean"], sd[f"{name}.bn.running_var"],
                             sd[f"{name}.bn.weight"], sd[f"{name}.bn.bias"], eps=0.001)
            z = F.relu(z)
        if maxpool:
            z = F.max_pool2d(z, 3, 2)
        return z[0].permute(1, 2, 0).reshape(-1, 64).double().numpy()

    a, b = feats(x), feats(y)
    m1, m2, s1, s2 = a.mean(0), b.mean(0), np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    covmean = linalg.sqrtm(s1 @ s2).real
    return float(np.sum((m1 - m2) ** 2) + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


@pytest.fixture(scope="module")
def inception_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("sifid") / "inception_v3_google-test.pth"
    torch.save(_inception_state_dict(), p)
    return p


@pytest.mark.parametrize("variant,maxpool", [("singan", False), ("pytorch-fid", True)])
def test_sifid_matches_singan_recipe(inception_file, variant, maxpool):
    rng = np.random.default_rng(8)
    x = rng.random((48, 56, 3))
    y = np.clip(0.6 * x + 0.2 + 0.05 * rng.standard_normal(x.shape), 0, 1)
    model = load_sifid_inception(inception_file, variant)
    got = sifid(x.astype(np.float32), y.astype(np.float32), model).item()
    expected = _sifid_reference(x, y, _inception_state_dict(), maxpool)
    assert got == pytest.approx(expected, rel=1e-4)
    assert sifid(x, x, model).item() == 0.0
    assert model.weights_sha256 == weights_sha256(inception_file)


def test_sifid_layouts_sizes_and_scaling(tmp_path, inception_file):
    torch.save({"state_dict": _inception_state_dict(prefix="module.")}, tmp_path / "wrapped.pth")
    x, y = _images(2, 40, 40, 9)
    a = sifid(x, y, weights=inception_file)
    assert a.shape == (2,) and a.dtype == torch.float64 and (a > 0).all()
    assert torch.allclose(sifid(x, y, weights=tmp_path / "wrapped.pth"), a)
    assert sifid(x, y[:, :, :36, :33], weights=inception_file).shape == (2,)  # different sizes are fine
    tiny = sifid(x, y, weights=inception_file, input_scale=1 / 255)  # SinGAN-on-PNG emulation
    assert (tiny < a).all()
    black = torch.zeros(1, 3, 32, 32)
    assert sifid(black, black, weights=inception_file).item() == 0.0
    assert np.isfinite(sifid(black, torch.ones_like(black), weights=inception_file).item())
    row = compute_metrics(x[:1], y[:1], ["sifid"], {"sifid": inception_file})
    assert row["sifid"] == pytest.approx(a[0].item()) and row["sifid_variant"] == "singan"
    assert row["sifid_weights_sha256"] == weights_sha256(inception_file)


def test_sifid_missing_or_wrong_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    with pytest.raises(CamoError, match="inception_v3_google"):
        load_sifid_inception()
    with pytest.raises(CamoError, match="no local inception"):
        compute_metrics(np.zeros((40, 40, 3)), np.zeros((40, 40, 3)), ["sifid"])
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "tf_layout.pth")
    with pytest.raises(CamoError, match="Conv2d_1a_3x3.conv.weight"):
        load_sifid_inception(tmp_path / "tf_layout.pth")
    with pytest.raises(CamoError, match="unknown SIFID variant"):
        load_sifid_inception(tmp_path / "tf_layout.pth", variant="fid-2048")
    ckpt = tmp_path / "hub" / "checkpoints"
    ckpt.mkdir(parents=True)
    torch.save(_inception_state_dict(), ckpt / "pt_inception-2015-12-05-6726825d.pth")
    assert load_sifid_inception().weight_path.endswith("pt_inception-2015-12-05-6726825d.pth")


# ---------------------------------------------------------------- DreamSim


def test_dreamsim_error_paths(tmp_path):
    with pytest.raises(CamoError, match="local weights folder"):
        load_dreamsim(None)
    with pytest.raises(CamoError, match="not found"):
        load_dreamsim(tmp_path / "nope")
    (tmp_path / "ensemble_lora").mkdir()
    with pytest.raises(CamoError, match="lacks: dino_vitb16_pretrain.pth"):
        load_dreamsim(tmp_path)
    with pytest.raises(CamoError, match="unknown DreamSim type"):
        load_dreamsim(tmp_path, "vit-huge")
    with pytest.raises(CamoError, match="local weights folder"):
        compute_metrics(np.zeros((40, 40, 3)), np.zeros((40, 40, 3)), ["dreamsim"], {})
