"""Reward encoders: shapes, determinism, the latent reward, VAE training, VGG loading, errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from encoders import encoder_names, encoder_options, latent_reward, make_encoder
from encoders.conv import conv_output_size, drq_conv_stack
from encoders.options import VGG_WEIGHTS_ENV_VAR as WEIGHTS_ENV_VAR
from encoders.vgg import vgg16_features

torch.set_num_threads(1)

FAST_FIT = {"epochs": 1, "batch_size": 4}


def images(n: int, size: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, size, size, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def vgg_weights(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A random-weights VGG16 state dict in torchvision's key format (with a classifier)."""
    torch.manual_seed(0)
    state = {f"features.{k}": v for k, v in vgg16_features().state_dict().items()}
    state["classifier.0.weight"] = torch.zeros(4, 25088)  # ignored, as in a full model
    path = tmp_path_factory.mktemp("vgg") / "vgg16.pth"
    torch.save(state, path)
    return str(path)


def build(name: str, size: int, seed: int = 0, vgg_weights: str = "", **options):
    if name == "vgg":
        options = {"weights_path": vgg_weights, "input_size": 64, **options}
    encoder = make_encoder(name, (size, size, 3), seed=seed, **options)
    if encoder.needs_fit:
        encoder.fit(images(4, size, seed=1), progress=False)
    return encoder


def learned_options(name: str) -> dict:
    return FAST_FIT if name in ("vae", "cvae") else {}


def test_registry_lists_the_six_encoders() -> None:
    assert encoder_names() == ("pixel", "linear", "conv", "vae", "cvae", "vgg")
    assert dataclasses.asdict(encoder_options("vae")()) == {
        "latent_dim": 16,
        "beta": 1.0,
        "lr": 1e-3,
        "epochs": 20,
        "num_images": 2000,
        "batch_size": 64,
    }
    assert dataclasses.asdict(encoder_options("linear")()) == {"latent_dim": 128}


#: a value other than the default for every declared option of every encoder
NON_DEFAULT = {
    "pixel": {},
    "linear": {"latent_dim": 7},
    "conv": {"latent_dim": 7, "init": "pytorch"},
    "vae": {"latent_dim": 8, "beta": 2.5, "lr": 2e-3, "epochs": 2, "num_images": 9,
            "batch_size": 3},
    "cvae": {"latent_dim": 8, "beta": 2.5, "lr": 2e-3, "epochs": 2, "num_images": 9,
             "batch_size": 3},
    "vgg": {"input_size": 64},
}  # fmt: skip


@pytest.mark.parametrize("name", ["pixel", "linear", "conv", "vae", "cvae", "vgg"])
def test_an_encoder_is_built_with_its_declared_options(name: str, vgg_weights) -> None:
    given = dict(NON_DEFAULT[name], **({"weights_path": vgg_weights} if name == "vgg" else {}))
    declared = dataclasses.fields(encoder_options(name))
    assert {f.name for f in declared} == set(given), "give every option a non-default value"
    for field in declared:
        assert field.name == "weights_path" or given[field.name] != field.default, field.name
    encoder = make_encoder(name, (48, 48, 3), **given)
    assert encoder.options == encoder_options(name)(**given)
    # what the encoder does with them
    if "latent_dim" in given:
        assert encoder.dim == given["latent_dim"]
    if name == "conv":  # PyTorch's init: random biases (DrQ's: zero)
        assert encoder.net[0][0].bias.detach().abs().max() > 0
    if name in ("vae", "cvae"):
        assert encoder.num_images == 9  # read by the trial, which collects that many frames
        report = encoder.fit(images(7, 48), progress=False)
        assert report.epochs == 2 and len(report.losses) == 2
        for option in ("beta", "lr", "batch_size"):  # each one changes the training
            default = next(f.default for f in declared if f.name == option)
            other = make_encoder(name, (48, 48, 3), **{**given, option: default})
            assert other.fit(images(7, 48), progress=False).losses != report.losses, option
    if name == "vgg":
        assert encoder.dim == 512 * 2 * 2  # 64 / 2^5 = 2 per side
        assert encoder.encode(images(1, 48)).shape == (1, 2048)


def test_a_registered_encoder_without_declared_options_takes_none() -> None:
    from encoders import registry

    registry.register("pixel_copy", "encoders.pixel:PixelEncoder")
    try:
        assert "pixel_copy" in encoder_names()
        assert dataclasses.asdict(encoder_options("pixel_copy")()) == {}
        assert make_encoder("pixel_copy", image_shape=(8, 8, 3)).encode(
            np.zeros((1, 8, 8, 3), np.uint8)
        ).shape == (1, 192)
    finally:
        del registry._REGISTRY["pixel_copy"]


@pytest.mark.parametrize("size", [48, 84])
@pytest.mark.parametrize("name", ["pixel", "linear", "conv", "vae", "cvae", "vgg"])
def test_shapes_determinism_and_zero_self_distance(name: str, size: int, vgg_weights) -> None:
    x = images(5, size)
    a = build(name, size, vgg_weights=vgg_weights, **learned_options(name))
    b = build(name, size, vgg_weights=vgg_weights, **learned_options(name))
    za, zb = a.encode(x), b.encode(x)
    assert za.shape == (5, a.dim) and za.dtype == np.float32
    np.testing.assert_array_equal(za, zb)  # same seed, same encoding
    np.testing.assert_array_equal(latent_reward(za, za), np.zeros(5, np.float32))
    # the batch it is in changes an encoding only by float rounding
    np.testing.assert_allclose(za[2:3], a.encode(x[2:3]), rtol=1e-4, atol=1e-4)
    if name in ("linear", "conv", "vae", "cvae") and size == 48:
        c = build(name, size, seed=1, **learned_options(name))
        assert not np.allclose(c.encode(x), za)  # the seed matters


@pytest.mark.parametrize(
    ("name", "dims"),
    [
        ("pixel", {48: 6912, 84: 21168}),
        ("linear", {48: 128, 84: 128}),
        ("conv", {48: 128, 84: 128}),
        ("cvae", {48: 16, 84: 16}),
        ("vae", {48: 16, 84: 16}),
    ],
)
def test_dims(name: str, dims: dict[int, int]) -> None:
    for size, dim in dims.items():
        assert make_encoder(name, (size, size, 3), seed=0).dim == dim


def test_latent_dim_option() -> None:
    assert make_encoder("linear", (48, 48, 3), latent_dim=256).dim == 256
    encoder = build("cvae", 48, latent_dim=8, **FAST_FIT)
    assert encoder.encode(images(2, 48)).shape == (2, 8)


def test_pixel_is_flattened_and_scaled() -> None:
    x = np.zeros((1, 32, 32, 3), np.uint8)
    x[0, 0, 1, 2] = 255
    x[0, 1, 0, 0] = 51
    z = make_encoder("pixel", (32, 32, 3)).encode(x)
    assert z[0, 5] == 1.0 and z[0, 96] == pytest.approx(0.2) and z.sum() == pytest.approx(1.2)


def test_latent_reward_hand_computed() -> None:
    phi_next = np.array([[3.0, 4.0], [1.0, 1.0]], np.float32)
    np.testing.assert_allclose(latent_reward(phi_next, np.zeros(2)), [-5.0, -np.sqrt(2)])
    goals = np.array([[3.0, 4.0], [1.0, 2.0]])
    np.testing.assert_allclose(latent_reward(phi_next, goals), [0.0, -1.0])
    assert latent_reward(phi_next, goals).dtype == np.float32


def test_drq_conv_sizes() -> None:
    assert conv_output_size(84) == 35 and conv_output_size(48) == 17
    out = drq_conv_stack(3, 32)(torch.zeros(2, 3, 84, 84))
    assert out.shape == (2, 32, 35, 35)
    with pytest.raises(ValueError, match="too small"):
        conv_output_size(8)


@pytest.mark.parametrize("size", [48, 84, 64, 50])
def test_cvae_decoder_reconstructs_the_input_size(size: int) -> None:
    encoder = make_encoder("cvae", (size, size, 3), seed=0)
    z = torch.zeros(2, encoder.latent_dim)
    assert encoder.decoder_net(z).shape == (2, 3, size, size)


def test_cvae_has_the_rig_layout_at_48() -> None:
    encoder = make_encoder("cvae", (48, 48, 3), seed=0)
    assert encoder.encoder_net[-1].in_features == 576
    assert encoder.decoder_net[-1].kernel_size == (6, 6)


@pytest.mark.parametrize("name", ["vae", "cvae"])
def test_vae_loss_goes_down_and_fit_is_deterministic(name: str) -> None:
    # a tiny dataset: 8 dark flat-coloured images (far from the untrained grey output)
    colours = np.random.default_rng(0).integers(0, 64, (8, 1, 1, 3), dtype=np.uint8)
    x = np.ascontiguousarray(np.broadcast_to(colours, (8, 32, 32, 3)))
    options = {"epochs": 8, "batch_size": 4, "lr": 3e-3, "beta": 0.1}
    reports = [make_encoder(name, (32, 32, 3), **options).fit(x, progress=False) for _ in "ab"]
    losses = reports[0].losses
    assert reports[0].epochs == 8 and len(losses) == 8
    assert losses[-1] < 0.7 * losses[0]
    assert reports[0].losses == reports[1].losses  # same seed, same training on CPU
    assert set(reports[0].extra) == {"recon", "kl", "active_dims"}


def test_active_dims_counts_the_latent_dimensions_that_vary_over_the_data() -> None:
    from encoders.vae import ACTIVE_VARIANCE, active_dims

    rng = np.random.default_rng(0)
    means = np.stack([rng.normal(0, 1, 500), np.full(500, 3.0), rng.normal(0, 0.01, 500)], 1)
    assert active_dims(means) == 1  # the constant and the barely moving one are inactive
    assert active_dims(means, threshold=1e-5) == 2
    assert active_dims(np.zeros((4, 16))) == 0 and ACTIVE_VARIANCE == 0.01


@pytest.mark.parametrize("name", ["vae", "cvae"])
def test_a_fit_collapsed_onto_its_prior_has_no_active_dimension(name: str) -> None:
    """With a KL weight that outweighs every pixel the posterior mean stops moving with the
    image; with a small one the same data keeps latent dimensions in use."""
    colours = np.random.default_rng(0).integers(0, 256, (16, 1, 1, 3), dtype=np.uint8)
    x = np.ascontiguousarray(np.broadcast_to(colours, (16, 32, 32, 3)))
    options = {"epochs": 30, "batch_size": 8, "lr": 3e-3, "latent_dim": 8}
    used = make_encoder(name, (32, 32, 3), beta=0.1, **options).fit(x, progress=False)
    collapsed = make_encoder(name, (32, 32, 3), beta=1e4, **options).fit(x, progress=False)
    assert used.extra["active_dims"] >= 1
    assert collapsed.extra["active_dims"] == 0 and collapsed.extra["kl"] < 0.01


def test_fit_prints_progress(capsys: pytest.CaptureFixture) -> None:
    make_encoder("cvae", (32, 32, 3), epochs=2).fit(images(4, 32))
    err = capsys.readouterr().err
    assert "[cvae] epoch 1/2 loss" in err and "epoch 2/2" in err


def test_learned_encoder_must_be_fit_first() -> None:
    with pytest.raises(RuntimeError, match="fit"):
        make_encoder("vae", (32, 32, 3)).encode(images(1, 32))


def test_learning_free_fit_is_a_no_op() -> None:
    encoder = make_encoder("conv", (48, 48, 3))
    before = encoder.encode(images(2, 48))
    assert encoder.fit(images(2, 48)).losses == ()
    np.testing.assert_array_equal(before, encoder.encode(images(2, 48)))


def test_vgg_default_input_size_and_env_var(vgg_weights, monkeypatch) -> None:
    monkeypatch.setenv(WEIGHTS_ENV_VAR, vgg_weights)
    encoder = make_encoder("vgg", (48, 48, 3))
    assert encoder.dim == 512 * 7 * 7
    assert encoder.encode(images(1, 48)).shape == (1, 25088)


def test_vgg_errors_say_where_to_put_the_weights(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv(WEIGHTS_ENV_VAR, raising=False)
    with pytest.raises(ValueError, match=f"weights_path.*{WEIGHTS_ENV_VAR}"):
        make_encoder("vgg", (48, 48, 3))
    with pytest.raises(ValueError, match=r"does not exist.*vgg16-397923af\.pth"):
        make_encoder("vgg", (48, 48, 3), weights_path=str(tmp_path / "missing.pth"))
    bad = tmp_path / "bad.pth"
    torch.save({"features.0.weight": torch.zeros(64, 3, 5, 5)}, bad)
    with pytest.raises(ValueError, match=r"not a torchvision VGG16 state dict.*features\.0"):
        make_encoder("vgg", (48, 48, 3), weights_path=str(bad))
    garbage = tmp_path / "garbage.pth"
    garbage.write_text("not a torch file")
    with pytest.raises(ValueError, match="not a torch state dict"):
        make_encoder("vgg", (48, 48, 3), weights_path=str(garbage))


def test_bad_names_options_and_inputs_are_clear_errors() -> None:
    with pytest.raises(ValueError, match=r"unknown encoder 'cnv'.*'conv'.*pixel, linear, conv"):
        make_encoder("cnv", (48, 48, 3))
    with pytest.raises(ValueError, match=r"no option\(s\) \['latent'\].*latent_dim"):
        make_encoder("linear", (48, 48, 3), latent=3)
    with pytest.raises(ValueError, match=r"latent_dim must be one of \(8, 16\), got 32"):
        make_encoder("vae", (48, 48, 3), latent_dim=32)
    with pytest.raises(ValueError, match=r"'cvae'.*beta must be greater than 0, got -1\.0"):
        make_encoder("cvae", (48, 48, 3), beta=-1.0)
    with pytest.raises(ValueError, match=r"'cvae'.*epochs must be a valid integer, got 1\.5"):
        make_encoder("cvae", (48, 48, 3), epochs=1.5)
    with pytest.raises(
        ValueError, match=r"'conv'.*latent_dim must be greater than or equal to 1, got 0"
    ):
        make_encoder("conv", (48, 48, 3), latent_dim=0)
    with pytest.raises(ValueError, match=r"'vgg'.*input_size must be greater than or equal to 32"):
        make_encoder("vgg", (48, 48, 3), weights_path="unused.pth", input_size=16)
    with pytest.raises(ValueError, match="device"):
        make_encoder("conv", (48, 48, 3), device="tpu")
    encoder = make_encoder("pixel", (48, 48, 3))
    with pytest.raises(ValueError, match="uint8"):
        encoder.encode(np.zeros((1, 48, 48, 3), np.float32))
    with pytest.raises(ValueError, match="shape"):
        encoder.encode(np.zeros((1, 84, 84, 3), np.uint8))


def test_conv_drq_init_is_orthogonal_with_relu_gain_and_zero_biases() -> None:
    """DrQ's weight_init (denisyarats/drq, facebookresearch/drqv2): each layer's weight,
    flattened to [out, in*k*k], has orthonormal rows times the gain (sqrt(2) on the convs,
    1 on the Linear); every bias is zero."""
    encoder = make_encoder("conv", (48, 48, 3), seed=3, latent_dim=16)
    assert encoder.options.init == "drq"  # the default: the thesis' CONV
    layers = [m for m in encoder.net.modules() if isinstance(m, torch.nn.Conv2d | torch.nn.Linear)]
    assert [type(m).__name__ for m in layers] == ["Conv2d"] * 4 + ["Linear"]
    for layer in layers:
        gain = 2**0.5 if isinstance(layer, torch.nn.Conv2d) else 1.0
        w = layer.weight.detach().reshape(len(layer.weight), -1).double()
        gram = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w  # the smaller side
        eye = torch.eye(len(gram), dtype=torch.double)
        torch.testing.assert_close(gram, gain**2 * eye, atol=1e-5, rtol=0)  # float32 weights
        assert not layer.bias.detach().any()


def test_conv_init_is_deterministic_per_seed_and_pytorch_init_is_an_option() -> None:
    x = images(3, 48)
    drq = [make_encoder("conv", (48, 48, 3), seed=s, latent_dim=8).encode(x) for s in (0, 0, 1)]
    np.testing.assert_array_equal(drq[0], drq[1])
    assert not np.allclose(drq[0], drq[2])
    pytorch = make_encoder("conv", (48, 48, 3), seed=0, latent_dim=8, init="pytorch")
    assert pytorch.options.init == "pytorch"
    biases = [m.bias for m in pytorch.net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert all(b.detach().abs().max() > 0 for b in biases)  # PyTorch's default: random biases
    again = make_encoder("conv", (48, 48, 3), seed=0, latent_dim=8, init="pytorch")
    np.testing.assert_array_equal(pytorch.encode(x), again.encode(x))
    assert not np.allclose(pytorch.encode(x), drq[0])
    with pytest.raises(ValueError, match=r"'conv' option init must be one of \('drq', 'pytorch'\)"):
        make_encoder("conv", (48, 48, 3), init="xavier")
