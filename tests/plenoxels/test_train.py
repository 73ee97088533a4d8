"""The training loop's parts: batches of real pixels, the learning-rate schedule, TV for few views, the background's
texture size, the pruning pass's rays."""
import copy
import dataclasses
import math

import numpy as np
import pytest
import torch

from stages.common.frames import load_frame
from stages.common.json_files import read_json
from stages.scoring.metrics import image_psnr
from plenoxels.core.cameras import Intrinsics, look_at, rays_from_camera
from plenoxels.core.errors import UserError
from plenoxels.core.grid import SparseGrid
from plenoxels.core.native import cuda_ready
from plenoxels.core.optim import GridGrad, decayed_lr
from plenoxels.core.render import RenderOptions, loss_and_grad
from plenoxels.core.regularizers import tv_scale_for_views, views_per_point
from plenoxels.core.scene_model import ModelOptions, SceneModel, background_width_for
from plenoxels.core.schedule import Schedule
from plenoxels.core.train import Diverged, Fitter, TrainOptions, prune_mask, pruning_rays, pruning_stride
from plenoxels.core.ray_set import RaySet, coherent_order, random_backdrops
from tests.stages.test_fit import make_scene


def training_rays(root, frames: list[dict]) -> RaySet:
    """The frames' photos, full size on white, as the fit's training rays."""
    loaded = [load_frame(root, frame, 1.0, (1.0, 1.0, 1.0)) for frame in frames]
    return RaySet([image for image, _ in loaded], [np.asarray(f["transform_matrix"]) for f in frames],
                  [k for _, k in loaded])


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not cuda_ready(),
                                                               reason="needs an NVIDIA GPU and a CUDA build"))]


@pytest.mark.parametrize("device", DEVICES)
def test_batches_are_the_rays_and_colours_of_real_pixels(tmp_path, device):
    root = make_scene(tmp_path)
    frames = [f for f in read_json(root / "normalize" / "scene.json")["frames"] if f["split"] == "train"]
    train = training_rays(root, frames)
    on_device = train.to(torch.device(device))
    for mode in ("tiles", "rays"):
        drawn = on_device.batch(1024, mode, 16, torch.Generator().manual_seed(3))
        assert all(t.device.type == device for t in drawn)  # made where the set lives
        o, d, colour = (t.cpu() for t in drawn)
        # The same batch on every device: the draws come from the CPU generator.
        for got, want in zip((o, d, colour), train.batch(1024, mode, 16, torch.Generator().manual_seed(3))):
            torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-6)
        # Every ray of the batch is the ray of some pixel whose colour is the target (the camera of the first ray).
        camera = int((train.c2w[:, :3, 3] - o[0]).norm(dim=1).argmin())
        all_o, all_d = rays_from_camera(train.c2w[camera].double().numpy(), train.intrinsics[camera])
        first = (o - train.c2w[camera, :3, 3]).norm(dim=1) < 1e-6
        match = torch.cdist(d[first].double(), all_d.reshape(-1, 3).double()).min(dim=1)
        assert float(match.values.max()) < 1e-5
        pixels = train.pixels[train.offsets[camera]: train.offsets[camera + 1]].float() / 255
        np.testing.assert_allclose(colour[first].numpy(), pixels[match.indices].numpy(), atol=1e-6)
    o, d, _ = on_device.batch(16 * 16, "tiles", 16, torch.Generator().manual_seed(3))
    # One tile: one camera, neighbouring pixels.
    assert (o == o[0]).all()
    # A pruning pass's rays are the same wherever the set lives.
    for got, want in zip(on_device.strided_rays(3), train.strided_rays(3)):
        assert got.device.type == device
        torch.testing.assert_close(got.cpu(), want, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("coherent", [False, True])
def test_a_batch_carries_each_rays_photos_own_backdrop(coherent):
    # Three flat photos, each of its own backdrop colour: a ray's backdrop is then its own target colour.
    colours = [[1.0, 1.0, 1.0], [0.05, 0.05, 0.05], [0.2, 0.6, 0.9]]
    k = Intrinsics(fl_x=20.0, fl_y=20.0, cx=8.0, cy=6.0, w=16, h=12)
    c2ws = [look_at((3 * math.cos(a), 3 * math.sin(a), 0.5), (0, 0, 0)) for a in (0.0, 2.0, 4.0)]
    images = [np.broadcast_to(np.asarray(c, dtype=np.float32), (12, 16, 3)).copy() for c in colours]
    train = RaySet(images, c2ws, [k] * 3, colours)
    for mode in ("rays", "tiles"):
        o, d, target, backdrop = train.batch(512, mode, 8, torch.Generator().manual_seed(1), coherent,
                                             with_backdrops=True)
        assert backdrop.shape == target.shape == (len(o), 3)
        torch.testing.assert_close(backdrop, target, atol=1 / 255, rtol=0)
        assert len({tuple(c) for c in backdrop.round(decimals=2).tolist()}) > 1  # the photos' colours, not one
    picked = train.subset([2, 0])
    assert picked.backdrop(0) == pytest.approx(colours[2]) and picked.backdrop(1) == pytest.approx(colours[0])
    assert RaySet(images, c2ws, [k] * 3).backdrop(0) is None


@pytest.mark.parametrize("coherent", [False, True])
def test_a_batch_carries_each_rays_mask_cover_and_random_backdrops_go_behind_the_empty_and_some_covered(coherent):
    # Photos white where their masks cover nothing, pink where they cover a part and red where they cover all: a ray's
    # cover tells its target.
    k = Intrinsics(fl_x=20.0, fl_y=20.0, cx=8.0, cy=6.0, w=16, h=12)
    c2ws = [look_at((3 * math.cos(a), 3 * math.sin(a), 0.5), (0, 0, 0)) for a in (0.0, 2.0, 4.0)]
    rng = np.random.default_rng(0)
    cover = [rng.choice(np.array([0, 128, 255], np.uint8), size=(12, 16), p=[share, 0.2, 0.8 - share])
             for share in (0.2, 0.4, 0.6)]
    red, pink = np.asarray([0.8, 0.1, 0.1]), np.asarray([0.9, 0.55, 0.55])
    images = [np.select([c[..., None] == 0, c[..., None] == 128], [np.ones(3), pink], red).astype(np.float32)
              for c in cover]
    train = RaySet(images, c2ws, [k] * 3, cover=cover)
    for mode in ("rays", "tiles"):
        o, d, target, flags = train.batch(512, mode, 8, torch.Generator().manual_seed(1), coherent, with_cover=True)
        assert flags.dtype == torch.uint8 and flags.shape == (len(o),)
        empty, whole, part = flags == 0, flags == 255, flags == 128
        assert torch.equal(empty, (target > 0.99).all(dim=1)) and torch.equal(whole, (target[:, 1] < 0.2))
        assert 0 < int(empty.sum()) and 0 < int(part.sum()) and 0 < int(whole.sum())
        background = torch.ones(3).expand(len(o), 3)
        seen, trained = random_backdrops(flags, background, target, 0.5, torch.Generator().manual_seed(2))
        assert torch.equal(trained[~empty], target[~empty])  # a covered ray's target is its photo's
        assert torch.equal(seen[empty], trained[empty])  # an empty ray is right where it lets the backdrop through
        assert float(seen[empty].std(dim=0).min()) > 0.15 and 0 <= float(seen.min()) and float(seen.max()) <= 1
        assert (seen[part] == 1).all()  # a pixel covered in part holds its backdrop's share: that backdrop stays
        behind_whole = (seen[whole] != 1).any(dim=1).float().mean()
        assert 0.35 < float(behind_whole) < 0.65  # half those covered whole see a random colour
        seen, _ = random_backdrops(flags, background, target, 0.0, torch.Generator().manual_seed(2))
        assert (seen[~empty] == 1).all()
    picked = train.subset([2, 0])
    assert torch.equal(picked.cover, torch.cat([torch.from_numpy(cover[2]).reshape(-1),
                                                torch.from_numpy(cover[0]).reshape(-1)]))
    assert RaySet(images, c2ws, [k] * 3).batch(8, "rays", 8, torch.Generator(), with_cover=True)[-1] is None


def test_learning_rate_schedule():
    assert math.isclose(decayed_lr(30.0, 0.05, 0.0), 30.0)  # svox2's density rates, as plain numbers
    assert math.isclose(decayed_lr(30.0, 0.05, 1.0), 0.05)
    assert math.isclose(decayed_lr(30.0, 0.05, 0.5), math.sqrt(30.0 * 0.05))
    assert decayed_lr(30.0, 0.05, 0.0, delay=0.2) == pytest.approx(0.3)
    assert decayed_lr(30.0, 0.05, 0.2, delay=0.2) == pytest.approx(decayed_lr(30.0, 0.05, 0.2))


def test_each_level_after_the_first_decays_the_rates_over_its_own_steps(tmp_path):
    schedule = Schedule([16, 32, 64], [100, 200, 300])
    # Over the whole fit: one decay, the density's ramp over its first steps.
    assert schedule.rate_progress(0, 0, per_level=False) == (0.0, True)
    assert schedule.rate_progress(300, 2, per_level=False) == (0.5, True)
    # Per level: the first level as over the whole fit, each later one from its start values to its final ones.
    assert schedule.rate_progress(50, 0, per_level=True) == (50 / 600, True)
    assert schedule.rate_progress(100, 1, per_level=True) == (0.0, False)
    assert schedule.rate_progress(200, 1, per_level=True) == (0.5, False)
    assert schedule.rate_progress(450, 2, per_level=True) == (0.5, False)

    root = make_scene(tmp_path, width=32)
    scene = read_json(root / "normalize" / "scene.json")
    train = training_rays(root, [f for f in scene["frames"] if f["split"] == "train"])

    def density_rates(per_level: bool) -> list[float]:
        options = TrainOptions(resolutions=[16, 32], steps=[20, 20], batch_size=256, lr_per_level=per_level)
        fitter = Fitter(SceneModel.create(scene, ModelOptions(), 16), options, train, schedule=Schedule.as_set(options))
        rates = []
        fitter.run(tmp_path / f"rates-{per_level}.pt", 1e9, on_step=lambda _: rates.append(fitter.optim.lr_density))
        return rates

    options = TrainOptions()
    per_level, whole = density_rates(True), density_rates(False)
    assert per_level[:20] == whole[:20]
    # The second level starts at the density's full rate (no ramp) and falls to its final one; over the whole fit
    # it would go on from halfway.
    assert per_level[20] == pytest.approx(options.lr_density)
    assert per_level[-1] == pytest.approx(decayed_lr(options.lr_density, options.lr_density_final, 19 / 20))
    assert whole[20] == pytest.approx(decayed_lr(options.lr_density, options.lr_density_final, 0.5))
    assert all(a > b for a, b in zip(per_level[20:], per_level[21:]))


def test_a_level_finer_than_the_density_rates_reference_steps_its_density_in_proportion(tmp_path):
    """lr_density_reference_resolution: a level finer than it takes the density's rates times (its resolution / the
    reference) at every step; coarser levels, the SH rates and every level with the reference at 0 keep them."""
    root = make_scene(tmp_path, width=32)
    scene = read_json(root / "normalize" / "scene.json")
    train = training_rays(root, [f for f in scene["frames"] if f["split"] == "train"])

    def rates(reference: int) -> list[tuple[float, float]]:
        options = TrainOptions(resolutions=[16, 32], steps=[10, 10], batch_size=256,
                               lr_density_reference_resolution=reference)
        fitter = Fitter(SceneModel.create(scene, ModelOptions(), 16), options, train, schedule=Schedule.as_set(options))
        seen = []
        fitter.run(tmp_path / f"rates-{reference}.pt", 1e9,
                   on_step=lambda _: seen.append((fitter.optim.lr_density, fitter.optim.lr_sh)))
        return seen

    as_set, referenced = rates(0), rates(16)
    assert len(as_set) == len(referenced) == 20
    assert referenced[:10] == as_set[:10]
    for (density, sh), (density_as_set, sh_as_set) in zip(referenced[10:], as_set[10:]):
        assert density == pytest.approx(2 * density_as_set) and sh == sh_as_set
    assert rates(32) == as_set  # no level finer than the reference
    with pytest.raises(UserError, match="lr_density_reference_resolution"):
        TrainOptions(lr_density_reference_resolution=-1).check()


def test_coherent_batches_are_the_same_rays_in_an_order_that_keeps_neighbours_together(tmp_path):
    root = make_scene(tmp_path)
    frames = [f for f in read_json(root / "normalize" / "scene.json")["frames"] if f["split"] == "train"]
    train = training_rays(root, frames)
    plain = train.batch(2048, "rays", 16, torch.Generator().manual_seed(5))
    ordered = train.batch(2048, "rays", 16, torch.Generator().manual_seed(5), coherent=True)
    # The same rays and targets, each once.
    key = lambda batch: sorted(map(tuple, torch.cat(batch, 1).tolist()))  # noqa: E731
    assert key(plain) == key(ordered)
    assert not torch.equal(plain[0], ordered[0])

    def spread(o, d):  # mean distance between consecutive rays' points closest to the centre
        u = d / d.norm(dim=1, keepdim=True)
        p = o - u * (o * u).sum(1, keepdim=True)
        return float((p[1:] - p[:-1]).norm(dim=1).mean())

    assert spread(*ordered[:2]) < 0.25 * spread(*plain[:2])
    # The grid's gradient is the same sum in another order.
    grid = SparseGrid.dense((24, 24, 24), (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 1, init_density=0.5)
    grid.data[:, 1:13] = torch.randn(grid.data.shape[0], 12, generator=torch.Generator().manual_seed(6)) * 0.3
    grads = []
    for o, d, target in (plain, ordered):
        grad = GridGrad(grid)
        loss, _ = loss_and_grad(grid, o, d, target, torch.ones_like(target), RenderOptions(), grad)
        grads.append((loss, grad.data.clone()))
    assert grads[0][0] == pytest.approx(grads[1][0], rel=1e-6)
    torch.testing.assert_close(grads[1][1], grads[0][1], atol=1e-7, rtol=1e-4)


def test_coherent_order_follows_a_space_filling_curve():
    # Rays whose points closest to the centre are a 4x4x4 lattice, shuffled (each ray runs square to its point's
    # direction from the centre): the order visits each octant's 8 points together.
    axis = torch.tensor([-0.75, -0.25, 0.25, 0.75])
    points = torch.cartesian_prod(axis, axis, axis)
    shuffled = points[torch.randperm(64, generator=torch.Generator().manual_seed(1))]
    dirs = torch.nn.functional.normalize(torch.linalg.cross(shuffled, torch.tensor([[0.3, -0.2, 1.0]]).expand(64, 3)), dim=1)
    origins = shuffled - 5 * dirs
    visited = shuffled[coherent_order(origins, dirs)]
    for start in range(0, 64, 8):
        octants = {tuple((p > 0).tolist()) for p in visited[start:start + 8]}
        assert len(octants) == 1


def test_coherent_order_sorts_by_the_interleaved_bits_of_the_closest_point():
    # The Morton code bit by bit, as its definition reads: bit b of axis a becomes bit 3b + a.
    gen = torch.Generator().manual_seed(2)
    origins, dirs = torch.randn(4096, 3, generator=gen) * 3, torch.randn(4096, 3, generator=gen)
    unit = dirs / dirs.norm(dim=1, keepdim=True)
    closest = origins - unit * (origins * unit).sum(1, keepdim=True)
    cell = ((closest.clamp(-2, 2) + 2) / 4 * 1023).long()
    code = torch.zeros(4096, dtype=torch.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cell[:, axis] >> bit) & 1) << (3 * bit + axis)
    order = coherent_order(origins, dirs)
    assert sorted(order.tolist()) == list(range(4096))
    assert bool((code[order][1:] >= code[order][:-1]).all())


def test_views_per_point_counts_the_cameras_that_see_the_box():
    k = Intrinsics(60.0, 60.0, 32.0, 32.0, 64, 64)
    around = [look_at([4 * math.cos(a), 4 * math.sin(a), 1.0], [0, 0, 0]) for a in np.linspace(0, 2 * math.pi, 12, endpoint=False)]
    away = [look_at([4 * math.cos(a), 4 * math.sin(a), 1.0], [8 * math.cos(a), 8 * math.sin(a), 1.0]) for a in (0.3, 2.0)]
    box = ([-0.5] * 3, [0.5] * 3)
    assert views_per_point(around, [k] * 12, *box) == pytest.approx(12, abs=0.5)
    assert views_per_point(around + away, [k] * 14, *box) == pytest.approx(12, abs=0.5)
    assert views_per_point(around[::4], [k] * 3, *box) == pytest.approx(3, abs=0.2)


def test_few_views_strengthen_tv_and_many_keep_it_as_set(tmp_path):
    assert tv_scale_for_views(40.0, 32.0, 3.0, 1000.0) == 1.0
    assert tv_scale_for_views(16.0, 32.0, 3.0, 1000.0) == pytest.approx(8.0)
    assert tv_scale_for_views(1.0, 32.0, 3.0, 1000.0) == 1000.0
    assert tv_scale_for_views(1.0, 0.0, 3.0, 1000.0) == 1.0
    root = make_scene(tmp_path)
    scene = read_json(root / "normalize" / "scene.json")
    frames = [f for f in scene["frames"] if f["split"] == "train"]
    scales = []
    for kept in (frames, frames[::4]):
        train = training_rays(root, kept)
        options = TrainOptions(tv_views=12.0)
        fitter = Fitter(SceneModel.create(scene, ModelOptions(), 16), options, train)
        tv = fitter.regularisation
        assert tv["views_per_point"] <= len(kept)
        assert tv["tv_density"] == pytest.approx(options.tv_density * tv["tv_scale"])
        assert tv["tv_sh"] == pytest.approx(options.tv_sh * tv["tv_scale"])
        scales.append(tv["tv_scale"])
    # 16 training views see the box about 12 times or more; a quarter of them (4) see no point more than 4 times, so
    # their TV is at least (12 / 4)^2 times as strong.
    assert scales[0] == pytest.approx(1.0, abs=0.3) and scales[1] >= (12.0 / len(frames[::4])) ** 2


def test_background_texels_follow_the_photos_pixels():
    assert background_width_for(138.0, 2.0) == 432  # 2 pi 138 / 2 = 433.5, a multiple of 8
    assert background_width_for(276.0, 2.0) == 2 * background_width_for(138.0, 2.0)  # twice the focal, twice the texels
    assert background_width_for(5.0, 2.0) == 64 and background_width_for(1e5, 2.0) == 2048
    assert background_width_for(None, 2.0) == 128


def test_a_pruning_pass_marches_rays_by_the_grid_not_the_photos_and_keeps_what_they_see(tmp_path):
    root = make_scene(tmp_path, width=160)
    scene = read_json(root / "normalize" / "scene.json")
    frames = [f for f in scene["frames"] if f["split"] == "train"]
    train = training_rays(root, frames)
    options = TrainOptions(resolutions=[32], steps=[150], batch_size=2048, prune_ray_scale=1.0)
    wanted = options.prune_rays_per_cell * 32 ** 2
    stride = pruning_stride(train.sizes, 32, options)
    # The sparsest lattice of pixels that still gives the wanted rays (16 photos of 160x120: every 4th pixel).
    assert stride > 1
    assert pruning_rays(train.sizes, 32, options) == train.strided_rays(stride)[0].shape[0] >= wanted
    assert train.strided_rays(stride + 1)[0].shape[0] < wanted
    # A pass in runs of whole photos marches the same rays in the same order, each run but the last the rays asked.
    whole = train.strided_rays(stride)
    per_photo = train.strided_rays(stride, range(1))[0].shape[0]
    runs = list(train.strided_ray_chunks(stride, 2 * per_photo + 1))  # three photos a run
    assert len(runs) == -(-len(train.sizes) // 3) and all(r[0].shape[0] == 3 * per_photo for r in runs[:-1])
    for got, want in zip((torch.cat([r[i] for r in runs]) for i in range(2)), whole):
        assert torch.equal(got, want)
    # A finer grid needs more rays, up to every pixel at prune_ray_scale; 0 asks for that always.
    assert pruning_stride(train.sizes, 64, options) < stride
    assert pruning_stride(train.sizes, 256, options) == 1
    assert pruning_stride(train.sizes, 32, dataclasses.replace(options, prune_rays_per_cell=0.0)) == 1
    assert pruning_stride(train.sizes, 256, dataclasses.replace(options, prune_ray_scale=0.25)) == 4

    fitter = Fitter(SceneModel.create(scene, ModelOptions(), 32), options, train)
    for _ in range(150):
        fitter.train_step()
    sparse = fitter.measure_weights()
    fitter.options = dataclasses.replace(options, prune_rays_per_cell=0.0)
    every_pixel = fitter.measure_weights()
    assert float(sparse.max()) > 0.5  # the fit has an opaque surface by now
    kept = prune_mask(fitter.model.grid, sparse, options)
    kept_by_every_pixel = prune_mask(fitter.model.grid, every_pixel, options)
    assert int(kept.sum()) < 0.5 * kept.numel()  # the empty box goes
    assert bool(kept[every_pixel > 0.5].all())   # and what the photos see clearly stays

    def rendered_psnr(keep: torch.Tensor) -> float:
        """Mean PSNR of the held-out and the first training views with only the `keep` rows."""
        model = copy.copy(fitter.model)
        model.grid = fitter.model.grid.prune(keep)[0]
        views = [f for f in scene["frames"] if f["split"] == "test"] + frames[:4]
        scores = []
        for frame in views:
            truth, k = load_frame(root, frame, 1.0, (1.0, 1.0, 1.0))
            with torch.no_grad():
                scores.append(image_psnr(model.render_camera(np.asarray(frame["transform_matrix"]), k)["rgb"].numpy(),
                                         truth))
        return float(np.mean(scores))

    # Pruned by the sparse pass, the photos and the held-out views render as they do pruned by every pixel.
    assert rendered_psnr(kept) == pytest.approx(rendered_psnr(kept_by_every_pixel), abs=0.05)


def test_a_repeated_resolution_prunes_the_grid_without_upsampling_it(tmp_path):
    """A level at the resolution of the one before: the pruning pass's voxels and no others, at the same shape, with
    the values and optimiser state they had; the next resolution then upsamples as usual."""
    root = make_scene(tmp_path, width=160)
    scene = read_json(root / "normalize" / "scene.json")
    frames = [f for f in scene["frames"] if f["split"] == "train"]
    train = training_rays(root, frames)
    options = TrainOptions(resolutions=[32, 32, 48], steps=[100, 20, 20], batch_size=2048)
    fitter = Fitter(SceneModel.create(scene, ModelOptions(), 32), options, train)
    for _ in range(100):
        fitter.train_step()
    grid, second_moment = fitter.model.grid, fitter.optim.second_moment.clone()
    keep = prune_mask(grid, fitter.measure_weights(), options)
    fitter.next_level()
    pruned = fitter.model.grid
    assert pruned.resolution == grid.resolution and pruned.num_occupied == int(keep.sum()) < 0.5 * grid.num_occupied
    assert torch.equal(pruned.data, grid.data[keep]) and torch.equal(fitter.optim.second_moment, second_moment[keep])
    assert fitter.levels[-1]["kept"] == fitter.levels[-1]["occupied"] == pruned.num_occupied
    for _ in range(20):
        fitter.train_step()
    fitter.next_level()
    assert max(fitter.model.grid.resolution) == 48 and fitter.model.grid.num_occupied > pruned.num_occupied


def test_an_upsampled_grid_keeps_what_its_own_pruning_pass_finds_and_its_rows_state(tmp_path):
    """An upsample then prunes on the finer grid's own render, before it trains: what is left is the upsampled grid's
    rows that the pass keeps, with their values and the optimiser state of the coarse vertex nearest each; the same
    upsample unpruned holds more rows for no better render of the training photos."""
    root = make_scene(tmp_path, width=160)
    scene = read_json(root / "normalize" / "scene.json")
    frames = [f for f in scene["frames"] if f["split"] == "train"]
    train = training_rays(root, frames)

    options = TrainOptions(resolutions=[32, 32, 64], steps=[100, 60, 60], batch_size=2048, prune_upsampled=True)
    kept = Fitter(SceneModel.create(scene, ModelOptions(), 32), options, train)
    for _ in range(160):
        kept.train_step()
        if kept.step == 100:
            kept.next_level()
    whole = copy.deepcopy(kept)  # the same fit up to the upsample
    whole.options = dataclasses.replace(options, prune_upsampled=False)
    kept.next_level()
    whole.next_level()
    upsampled, fine = whole.model.grid, kept.model.grid  # the upsample as it was before its own pass, and after
    keep = prune_mask(upsampled, kept.measure_weights(upsampled), options)
    assert max(fine.resolution) == 64 and fine.num_occupied == int(keep.sum()) < 0.8 * upsampled.num_occupied
    assert torch.equal(fine.data, upsampled.data[keep])
    assert torch.equal(kept.optim.second_moment, whole.optim.second_moment[keep])
    assert kept.levels[-1]["occupied"] == fine.num_occupied
    for fitter in (kept, whole):
        for _ in range(60):
            fitter.train_step()
    assert kept.train_psnr() > whole.train_psnr() - 0.3


def test_a_last_level_ends_once_its_train_psnr_has_stopped_rising_and_a_resumed_fit_keeps_the_shortened_level(
        tmp_path, monkeypatch):
    """The rule on a PSNR that rises 0.01 dB a step to step 250 and is flat after: with the level's window of 100 steps
    (a quarter of its 400) it ends at the first step whose last 100 rose less than 0.25 dB (326, past half the level),
    a tail of 40 steps after; never before half the level, not while it rises, not without converged_db, and a fit
    resumed from a checkpoint after it runs the level as shortened."""
    root = make_scene(tmp_path, width=32)
    scene = read_json(root / "normalize" / "scene.json")
    train = training_rays(root, [f for f in scene["frames"] if f["split"] == "train"])

    def walked(converged_db: float, flat_from: int = 250) -> Fitter:
        options = TrainOptions(resolutions=[16, 32], steps=[10, 400], batch_size=256, converged_db=converged_db)
        fitter = Fitter(SceneModel.create(scene, ModelOptions(), 16), options, train, schedule=Schedule.for_fit(options))
        monkeypatch.setattr(fitter, "train_psnr", lambda: 20 + 0.01 * min(fitter.step, flat_from))
        fitter.level = 1
        for step in range(10, 410):
            fitter.step = step + 1
            fitter.end_if_converged()
            if fitter.step == fitter.schedule.total_steps:
                break
        return fitter

    ended = walked(0.25)
    assert ended.converged == {"step": 326, "gain_db": pytest.approx(0.24), "window": 100, "tail": 40,
                               "steps_listed": 400, "steps_saved": 44}
    assert ended.schedule.steps == [10, 356] and ended.step == 366
    assert walked(0.0).schedule.steps == [10, 400] and walked(0.0).converged is None
    # Still rising: 0.01 dB a step is 1 dB a window. Flat from early on: it ends at half the level, not before.
    assert walked(0.5, flat_from=10 ** 6).converged is None
    assert walked(0.5, flat_from=150).converged["step"] == 10 + 200
    ended.step = 340
    ended.save_checkpoint(tmp_path / "ended.pt")
    options = ended.options
    resumed = Fitter(SceneModel.create(scene, ModelOptions(), 16), options, train, schedule=Schedule.for_fit(options))
    resumed.load_checkpoint(tmp_path / "ended.pt")
    assert resumed.schedule.steps == [10, 356] and resumed.converged == ended.converged


@pytest.mark.parametrize("ndc", ["off", "on"])
def test_a_train_step_scales_gradients_near_the_cameras_except_in_ndc(tmp_path, monkeypatch, ndc):
    """The step hands the kernels `near_gradient_distance` in a metric fit frame; NDC's frame is not metric (its
    depth runs 0-1 whatever the scene's size), so it gets none."""
    import plenoxels.core.train as train_module
    root = make_scene(tmp_path, width=32)
    scene = read_json(root / "normalize" / "scene.json")
    frames = [f for f in scene["frames"] if f["split"] == "train"]
    train = training_rays(root, frames)
    if ndc == "on":  # the synthetic scene's orbit is no forward capture, but one camera serves as NDC's reference
        scene["forward"] = {"reference_c2w": frames[0]["transform_matrix"], "near": 0.5}
    options = TrainOptions(resolutions=[16], steps=[2], batch_size=256, near_gradient_distance=0.7)
    fitter = Fitter(SceneModel.create(scene, ModelOptions(ndc=ndc), 16), options, train,
                    schedule=Schedule.for_fit(options))
    handed = []
    real = train_module.loss_and_grad

    def recording(*args, **kwargs):
        handed.append(kwargs["near_gradient"])
        return real(*args, **kwargs)

    monkeypatch.setattr(train_module, "loss_and_grad", recording)
    fitter.train_step()
    assert handed == [0.7 if ndc == "off" else 0.0]


def test_a_fit_ended_on_convergence_ends_with_its_rates_at_their_final_values(tmp_path):
    """Through Fitter.run, a last level that counts as converged at once (a threshold no fit stays under) ends a tenth
    of its steps after half of them, the rates decayed to their final values; a time budget's schedule (none set)
    runs every step."""
    root = make_scene(tmp_path, width=32)
    scene = read_json(root / "normalize" / "scene.json")
    train = training_rays(root, [f for f in scene["frames"] if f["split"] == "train"])
    options = TrainOptions(resolutions=[16, 16], steps=[10, 200], batch_size=256, converged_db=100.0)
    fitter = Fitter(SceneModel.create(scene, ModelOptions(), 16), options, train, schedule=Schedule.for_fit(options))
    fitter.run(tmp_path / "fit.pt", 1e9)
    assert fitter.step == fitter.schedule.total_steps == 10 + 100 + 20
    assert fitter.optim.lr_density == pytest.approx(options.lr_density_final, rel=0.02)
    assert fitter.optim.lr_sh == pytest.approx(options.lr_sh_final, rel=0.02)
    planned = Fitter(SceneModel.create(scene, ModelOptions(), 16), options, train,
                     schedule=Schedule(list(options.resolutions), list(options.steps)))
    planned.run(tmp_path / "planned.pt", 1e9)
    assert planned.step == 210 and planned.converged is None


# Gains kept whatever their first measure brings: what is checked is that a resumed fit measures them as a whole one.
@pytest.mark.parametrize("measures", [{}, {"photo_colour": True, "photo_colour_min_db": -100.0, "error_share": 0.5, "measure_every": 4}])
def test_a_fit_stopped_between_the_early_prune_and_the_upsample_resumes_to_the_same_model(tmp_path, measures):
    """On one thread (the gradient sums' order is then fixed), a fit stopped inside a repeated resolution's level and
    resumed from its checkpoint ends where the fit that never stopped does; so does one that measures its photos
    (their colours, the error map its batches draw from), between two measurements."""
    root = make_scene(tmp_path, width=64)
    scene = read_json(root / "normalize" / "scene.json")
    train = training_rays(root, [f for f in scene["frames"] if f["split"] == "train"])
    options = TrainOptions(resolutions=[16, 16, 32], steps=[30, 10, 10], batch_size=1024, **measures)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fits = [Fitter(SceneModel.create(scene, ModelOptions(), 16), options, train) for _ in range(3)]
        whole, stopped, resumed = fits
        whole.run(tmp_path / "whole.pt", 1e9)
        assert stopped.run(tmp_path / "stopped.pt", 1e9, stop_requested=lambda: stopped.step >= 35)
        assert stopped.level == 1 and list(stopped.model.grid.resolution) == whole.levels[0]["resolution"]
        resumed.load_checkpoint(tmp_path / "stopped.pt")
        resumed.run(tmp_path / "resumed.pt", 1e9)
    finally:
        torch.set_num_threads(before)
    assert resumed.levels == whole.levels
    assert torch.equal(resumed.model.grid.data, whole.model.grid.data)
    if measures:
        assert torch.equal(resumed.colour.gain, whole.colour.gain) and not bool(whole.colour.gain.eq(1).all())
        assert torch.equal(resumed.error_map.error, whole.error_map.error) and whole.error_map.measured
        assert torch.equal(resumed.error_map.left_out, whole.error_map.left_out)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_a_non_finite_parameter_is_found_wherever_it_is_and_padding_is_not_a_parameter(tmp_path, bad):
    root = make_scene(tmp_path)
    scene = read_json(root / "normalize" / "scene.json")
    fitter = Fitter(SceneModel.create(scene, ModelOptions(), 16), TrainOptions(resolutions=[16], steps=[1]),
                    training_rays(root, [f for f in scene["frames"] if f["split"] == "train"]))
    data = fitter.model.grid.data
    columns = 1 + 3 * (fitter.model.grid.sh_degree + 1) ** 2
    assert data.shape[1] > columns  # rows are padded
    fitter.check_finite()
    for row, column in ((0, 0), (data.shape[0] // 2, columns - 1), (data.shape[0] - 1, 1)):
        kept = float(data[row, column])
        data[row, column] = bad
        with pytest.raises(Diverged):
            fitter.check_finite()
        data[row, column] = kept
    data[data.shape[0] // 2, columns] = bad  # padding: no parameter
    fitter.check_finite()
