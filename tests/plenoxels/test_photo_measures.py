"""What the fit measures of its photos against the render: each photo's colour (gain and offset per channel) and the
error map a share of each batch is drawn from."""
import numpy as np
import torch

from stages.common.json_files import read_json
from plenoxels.core.cameras import Intrinsics
from plenoxels.core.error_map import ErrorMap, block_side, measure_stride
from plenoxels.core.photo_colour import (PhotoColour, PhotoGains, field_image, gain_field_lattice, gain_fields,
                                         lattice_shape)
from plenoxels.core.render import SH_C0
from plenoxels.core.scene_model import ModelOptions, SceneModel
from plenoxels.core.train import Fitter, TrainOptions
from plenoxels.core.ray_set import RaySet, as_bytes, clipped_bits
from tests.plenoxels.test_train import training_rays
from tests.stages.test_fit import make_scene


def test_each_photos_gains_are_found_and_clipped_pixels_say_nothing():
    gen = torch.Generator().manual_seed(0)
    photos, per_photo = 5, 4000
    gain = 0.7 + 0.6 * torch.rand(photos, 3, generator=gen, dtype=torch.float64)
    gain = gain / gain.mean(0)
    image = torch.arange(photos).repeat_interleave(per_photo)
    rendered = 0.1 + 0.7 * torch.rand(photos * per_photo, 3, generator=gen, dtype=torch.float64)
    photo = gain[image] * rendered
    # A fifth of each photo blown out: clipped at 1 whatever the render there, so it must not move the gains.
    blown = torch.rand(photos * per_photo, generator=gen) < 0.2
    photo[blown] = 1.0
    colour = PhotoColour(photos)
    colour.fit(image, rendered, photo)
    torch.testing.assert_close(colour.gain, gain, atol=1e-9, rtol=0)
    # Taken back to the common colour, each photo is the render again (where it is not clipped).
    torch.testing.assert_close(colour.to_common(image, photo)[~blown], rendered[~blown], atol=1e-9, rtol=0)
    assert colour.gain_db(image, rendered, photo) > 10
    # Noise in the render (a fit is never exact) leaves the gains where they were.
    noisy = rendered + 0.05 * torch.randn(rendered.shape, generator=gen, dtype=torch.float64)
    colour.fit(image, noisy, photo)
    torch.testing.assert_close(colour.gain, gain, atol=0.01, rtol=0)


def test_masked_photos_are_measured_inside_their_masks_and_keep_what_the_masks_put_in():
    """A photo cut out by its mask onto a backdrop: the object's pixels carry the photo's gain, the backdrop's share
    of each pixel none. The gains are measured inside the masks alone, and taking the photo back to the common colour
    leaves the masks' share as it is."""
    gen = torch.Generator().manual_seed(1)
    h, w, photos = 12, 16, 3
    gain = torch.tensor([[0.7, 0.8, 1.2], [1.0, 1.0, 1.0], [1.3, 1.2, 0.8]], dtype=torch.float64)
    object_colour = 0.2 + 0.6 * torch.rand(photos, h, w, 3, generator=gen, dtype=torch.float64)
    coverage = torch.zeros(photos, h, w, dtype=torch.float64)
    coverage[:, 3:9, 4:12] = 1.0
    coverage[:, 3:9, 4] = 0.5  # an edge the mask half covers
    behind = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.2, 0.9, 0.4]], dtype=torch.float64)
    photo = (coverage[..., None] * gain[:, None, None] * object_colour + (1 - coverage[..., None]) * behind[:, None, None]).clamp(0, 1)
    rays = RaySet([p.numpy() for p in photo], [np.eye(4)] * photos, [Intrinsics(20.0, 20.0, w / 2, h / 2, w, h)] * photos,
                  masks=[c.numpy() for c in coverage], behind=behind.tolist())
    image, row, col = rays.lattice(1)
    inside, put_in = rays.inside(image, row, col), rays.put_in(image, row, col).double()
    assert int(inside.sum()) == photos * 6 * 7
    # The render: the object in the common colour, the backdrop behind it where the mask is not.
    common = (coverage[..., None] * object_colour + (1 - coverage[..., None]) * behind[:, None, None])[image, row, col]
    *_, pixels = rays.pixel_rays(rays.flat(image, row, col))  # each pixel's photo colour comes last, with its ray
    pixels = pixels.double()
    colour = PhotoColour(photos)
    colour.fit(image, common, pixels, inside)
    torch.testing.assert_close(colour.gain, gain / gain.mean(0), atol=0.01, rtol=0)
    colour.gain = gain.clone()
    # One byte a channel: the colours and the masks' coverage are stored to 1/255.
    unclipped = (pixels < 1).all(1)
    torch.testing.assert_close(colour.to_common(image, pixels, put_in)[unclipped], common[unclipped], atol=0.02, rtol=0)
    outside = coverage[image, row, col] == 0
    torch.testing.assert_close(colour.to_common(image, pixels, put_in)[outside], behind[image[outside]], atol=0.005, rtol=0)
    # Over the whole composite, the gains would take the backdrop too.
    assert float((colour.to_common(image, pixels)[outside] - behind[image[outside]]).abs().max()) > 0.1
    # A subset keeps each photo's mask and backdrop.
    part = rays.subset([2])
    one = image == 2
    torch.testing.assert_close(part.put_in(image[one] * 0, row[one], col[one]), rays.put_in(image[one], row[one], col[one]))


def test_gains_stay_at_the_common_colour_where_a_photo_says_nothing():
    # Photo 1 is all clipped, photo 2 renders black: neither can be fitted, and no gain leaves its bounds.
    image = torch.tensor([0] * 100 + [1] * 100 + [2] * 100)
    rendered = torch.cat([torch.full((100, 3), 0.5), torch.full((100, 3), 0.5), torch.zeros(100, 3)])
    photo = torch.cat([torch.full((100, 3), 0.6), torch.ones(100, 3), torch.full((100, 3), 0.3)])
    colour = PhotoColour(3)
    colour.fit(image, rendered, photo)
    assert bool(torch.isfinite(colour.gain).all())
    torch.testing.assert_close(colour.gain[1], colour.gain[2])  # both at the common gain
    torch.testing.assert_close(colour.gain[0] / colour.gain[1], torch.full((3,), 1.2, dtype=torch.float64))


def test_a_photo_not_fitted_takes_the_gain_between_its_capture_neighbours():
    order = ["a", "b", "c", "d", "e", "f"]
    gains = PhotoGains(order, {"b": [1.0, 0.8, 1.2], "e": [0.7, 1.1, 1.2], "f": [0.6, 1.2, 1.3]})
    np.testing.assert_allclose(gains.of("b"), [1.0, 0.8, 1.2])  # a fitted photo keeps its own
    # c and d lie a third and two thirds of the way from b to e.
    np.testing.assert_allclose(gains.of("c"), [0.9, 0.9, 1.2])
    np.testing.assert_allclose(gains.of("d"), [0.8, 1.0, 1.2])
    np.testing.assert_allclose(gains.of("a"), [1.0, 0.8, 1.2])  # before the first fitted photo: the first one's
    np.testing.assert_allclose(gains.of("elsewhere"), [1.0, 1.0, 1.0])  # a camera of no photo: the common colour
    again = PhotoGains.from_record(gains.record())
    assert all(np.allclose(again.of(name), gains.of(name)) for name in order)
    assert PhotoGains.from_record(None) is None
    assert PhotoGains(order, {}).of("c").tolist() == [1.0, 1.0, 1.0]
    # Numbered without leading zeros, as a camera may: 9 lies between 8 and 10, whatever order the names came in.
    numbered = PhotoGains(["IMG_10", "IMG_11", "IMG_8", "IMG_9"],
                          {"IMG_8": [1.0] * 3, "IMG_10": [0.8] * 3, "IMG_11": [0.7] * 3})
    assert numbered.order == ["IMG_8", "IMG_9", "IMG_10", "IMG_11"]
    np.testing.assert_allclose(numbered.of("IMG_9"), [0.9] * 3)


def test_gains_that_do_not_follow_the_capture_order_leave_a_held_out_photo_in_the_common_colour():
    order = [f"{i:03d}" for i in range(40)]
    held_out = order[5::10]
    drift = {name: [0.8 + 0.01 * i] * 3 for i, name in enumerate(order) if name not in held_out}
    drifting = PhotoGains(order, drift)
    assert drifting.follows_order
    np.testing.assert_allclose(drifting.of("015"), [0.95] * 3)
    # The same gains shuffled among the photos: neighbours say nothing of each other, and a guess from them would
    # be further off than the common colour.
    names = list(drift)
    shuffled = dict(zip(names, [drift[names[i]] for i in np.random.default_rng(0).permutation(len(names))]))
    scattered = PhotoGains(order, shuffled)
    assert not scattered.follows_order
    np.testing.assert_allclose(scattered.of("015"), [1.0] * 3)
    np.testing.assert_allclose(scattered.of(names[3]), shuffled[names[3]])  # a fitted photo keeps its own


def test_the_error_map_draws_pixels_from_the_blocks_that_are_wrong():
    sizes = torch.tensor([[30, 40], [20, 20]])
    error_map = ErrorMap(sizes, stride=2)
    image, row, col = lattice(sizes, 2)
    # Wrong only in photo 1's block at rows 4-7, columns 8-11, and a little everywhere in photo 0.
    difference = torch.where((image == 1) & (row // 4 == 1) & (col // 4 == 2), 0.5, 0.0)
    difference = (difference + torch.where(image == 0, 1e-2, 0.0))[:, None].expand(-1, 3)
    error_map.measure(image, row, col, difference)
    drawn_image, drawn_row, drawn_col = error_map.draw(20000, torch.Generator().manual_seed(0))
    in_block = (drawn_image == 1) & (drawn_row // 4 == 1) & (drawn_col // 4 == 2)
    # Drawn in proportion to pixels x RMS error: 16 x 0.5 against 1200 x 0.01 for photo 0.
    share = 16 * 0.5 / (16 * 0.5 + 1200 * 0.01)
    assert abs(float(in_block.double().mean()) - share) < 0.02
    assert bool(((drawn_row < sizes[drawn_image, 0]) & (drawn_col < sizes[drawn_image, 1])).all())
    # Every pixel of the block is drawn, none outside it in photo 1.
    assert len({(r, c) for r, c in zip(drawn_row[in_block].tolist(), drawn_col[in_block].tolist())}) == 16
    assert not bool(((drawn_image == 1) & ~in_block).any())


def test_a_patch_the_render_disagrees_with_in_colour_is_left_out_and_blur_seams_specks_and_exposure_are_not():
    """What moved between photos shifts the colour of a patch of one photo away from what the others say is there;
    the detail a grid blurs is as often above the photo as below it, and averages out over a few blocks."""
    sizes = torch.tensor([[64, 80]] * 4)
    error_map = ErrorMap(sizes, stride=2)  # blocks of 4 pixels: 16 x 20 a photo
    image, row, col = lattice(sizes, 2)
    gen = torch.Generator().manual_seed(0)
    difference = 0.2 * (torch.randint(0, 2, (image.shape[0], 3), generator=gen) * 2 - 1).double()  # blurred detail
    person = (image == 0) & (row >= 20) & (row < 44) & (col >= 28) & (col < 44)  # 6 x 4 blocks
    difference[person] += torch.tensor([0.3, -0.2, 0.25], dtype=torch.float64)
    seam = (image == 1) & (col // 4 == 10)  # one block wide, the whole photo down
    difference[seam] += 0.2
    speck = (image == 2) & (row // 4 == 8) & (col // 4 == 8)  # one block
    difference[speck] += 0.6
    exposure = (image == 3) & (row < 44)  # most of a photo: its light, not something in front of it
    difference[exposure] += 0.3
    error_map.measure(image, row, col, difference)
    error_map.find_transients()
    left_out = ~error_map.kept(image, row, col)
    assert bool(left_out[person].all())
    around = (image == 0) & (row >= 16) & (row < 48) & (col >= 24) & (col < 48)  # a block's margin round the patch
    assert not bool((left_out & ~around).any())
    record = error_map.transients_record()
    assert record["photos"] == 1 and 24 * 16 / (4 * 64 * 80) <= record["share"] <= 32 * 24 / (4 * 64 * 80)
    # Measured again with the patch gone (the person walked on), the photo is whole again.
    difference[person] -= torch.tensor([0.3, -0.2, 0.25], dtype=torch.float64)
    error_map.measure(image, row, col, difference)
    error_map.find_transients()
    assert bool(error_map.kept(image, row, col).all()) and error_map.transients_record()["photos"] == 0


def test_a_small_person_is_found_where_each_measured_pixel_is_a_block_and_missed_on_blocks_of_four():
    """Where the map only finds what moved, each measured pixel is its own block: a person a few strides across is a
    patch of enough blocks to tell from a speck, where averaged over blocks of four it is not."""
    sizes = torch.tensor([[64, 80]] * 4)
    image, row, col = lattice(sizes, 2)
    gen = torch.Generator().manual_seed(1)
    difference = 0.1 * (torch.randint(0, 2, (image.shape[0], 3), generator=gen) * 2 - 1).double()  # blurred detail
    small = (image == 2) & (row >= 40) & (row < 54) & (col >= 20) & (col < 30)  # 7 x 5 measured pixels
    difference[small] += torch.tensor([0.3, -0.2, 0.25], dtype=torch.float64)
    speck = (image == 1) & (row == 31) & (col == 31)  # one measured pixel
    difference[speck] += 0.6
    found = {}
    for side in (2, 1):
        error_map = ErrorMap(sizes, stride=2, side=side)
        error_map.measure(image, row, col, difference)
        error_map.find_transients()
        found[side] = ~error_map.kept(image, row, col)
    assert not bool(found[2].any())
    assert bool(found[1][small].all())
    # Nothing else: the person and a margin of 2 blocks round it (the neighbours averaged, the block it is grown by).
    assert not bool((found[1] & ~((image == 2) & (row >= 36) & (row < 58) & (col >= 16) & (col < 34))).any())


def test_no_ray_is_drawn_from_what_is_left_out():
    h, w, photos = 24, 32, 3
    rows, cols = np.mgrid[0:h, 0:w]
    # Each pixel's colour says where it is: its row, its column and its photo.
    images = [np.stack([rows * 8, cols * 8, np.full_like(rows, 64 * i)], axis=-1).astype(np.uint8)
              for i in range(photos)]
    rays = RaySet(images, [np.eye(4)] * photos, [Intrinsics(20.0, 20.0, w / 2, h / 2, w, h)] * photos)
    error_map = ErrorMap(rays.sizes, stride=2)
    image, row, col = rays.lattice(2)
    out = (image == 1) & (row < 12) & (col < 16)
    difference = torch.where(out, 0.5, 0.01)[:, None].double().expand(-1, 3)
    error_map.measure(image, row, col, difference)
    error_map.left_out = torch.zeros_like(error_map.left_out)
    error_map.left_out[error_map.block_of(image[out], row[out], col[out])] = True
    for share in (0.0, 0.5):
        _, _, target = rays.batch(4096, "rays", 16, torch.Generator().manual_seed(0), error_map=error_map,
                                  error_share=share)
        drawn_row, drawn_col, drawn_image = (torch.round(target * 255) / torch.tensor([8, 8, 64])).round().long().T
        assert not bool(((drawn_image == 1) & (drawn_row < 12) & (drawn_col < 16)).any())
        # What is left out is a twelfth of the pixels: the rest of the batch is drawn.
        assert target.shape[0] >= 4096 * 0.8 and bool((drawn_image == 1).any())


def lattice(sizes: torch.Tensor, stride: int):
    """The pixels a measurement at this stride renders, of black photos of these sizes."""
    images = [np.zeros((h, w, 3), np.float32) for h, w in sizes.tolist()]
    k = [Intrinsics(10.0, 10.0, w / 2, h / 2, w, h) for h, w in sizes.tolist()]
    return RaySet(images, [np.eye(4)] * len(images), k).lattice(stride)


def test_the_measuring_stride_renders_about_the_rays_asked():
    sizes = torch.tensor([[400, 400]] * 100)
    stride = measure_stride(sizes, 1 << 17)
    pixels = 100 * 400 * 400
    assert (pixels / stride ** 2) >= (1 << 17) > pixels / (stride + 1) ** 2
    assert measure_stride(torch.tensor([[8, 8]]), 1 << 17) == 2  # never finer than blocks of MIN_BLOCK pixels
    # Each measured pixel its own block where the map only finds what moved, but never a block under MIN_BLOCK across.
    assert [block_side(stride, draws=False) for stride in (2, 3, 4, 8)] == [2, 2, 1, 1]
    assert [block_side(stride, draws=True) for stride in (2, 8)] == [2, 2]


def test_a_fit_of_photos_in_several_exposures_finds_each_photos_gains(tmp_path):
    """Photos of one scene, each in an exposure and white balance of its own: the fit with photo_colour finds each
    photo's gains; the fit without leaves them at 1."""
    root = make_scene(tmp_path, width=64)
    scene = read_json(root / "normalize" / "scene.json")
    frames = [f for f in scene["frames"] if f["split"] == "train"]
    plain = training_rays(root, frames)
    gen = torch.Generator().manual_seed(2)
    gains = 0.75 + 0.5 * torch.rand(len(plain), 3, generator=gen)
    gains = gains / gains.mean(0)
    images = [(plain.image(i) * gains[i]).clamp(0, 1).numpy() for i in range(len(plain))]
    exposed = RaySet(images, [np.asarray(f["transform_matrix"]) for f in frames], plain.intrinsics)
    fits = {}
    for used in (False, True):
        # SH degree 0: no view-dependent colour that could take up the photos' exposures instead.
        options = TrainOptions(resolutions=[24, 24, 32], steps=[60, 60, 120], batch_size=2048, photo_colour=used,
                               measure_every=40)
        fitter = Fitter(SceneModel.create(scene, ModelOptions(sh_degree=0), 24), options, exposed)
        fitter.run(tmp_path / f"{used}.pt", 1e9)
        fits[used] = fitter
    assert len(fits[True].colour_record()["measures"]) == 2  # decided on the first two (steps 40 and 60)
    found = fits[True].colour.gain.float()
    # The photos' own gains, as near as a fit of 20 dB renders them: in the same order, near their size.
    for channel in range(3):
        assert np.corrcoef(found[:, channel], gains[:, channel])[0, 1] > 0.8
    assert float((found - gains).abs().mean()) < 0.06 < float((gains - 1).abs().mean())
    record = fits[True].colour_record()
    assert record["used"] and record["gain_db"] > 0.5 and min(record["gain_min"]) < 0.95 < 1.05 < max(record["gain_max"])
    assert not fits[False].colour_record()["used"] and bool(fits[False].colour.gain.eq(1).all())
    # As it ends, the fit measures each photo's gains across its frame on the pixels the time budget kept time for.
    stride = gain_field_lattice(exposed.sizes, options.photo_colour_cells)[1]
    assert fits[True].gain_field_rays() == exposed.lattice(stride)[0].numel() > 0 == fits[False].gain_field_rays()
    assert fits[True].gain_fields().shape == (len(exposed), *lattice_shape(exposed.sizes, options.photo_colour_cells), 3)
    assert fits[False].gain_fields() is None


def test_a_batch_trains_each_photos_clipped_channels_as_floors_and_what_its_mask_put_in_as_a_target():
    gen = torch.Generator().manual_seed(4)
    images = [torch.randint(0, 250, (6, 8, 3), generator=gen, dtype=torch.uint8).numpy() for _ in range(2)]
    images[0][1, 2, 0] = images[0][4, 4, 2] = 255
    images[1][0, 0] = 254                          # within a byte of the top: every channel clipped
    images[1][5, 7] = 255                          # white the mask put in (its backdrop), not light the photo took
    coverage = [np.full((6, 8), 255, np.uint8) for _ in range(2)]
    coverage[1][5, 7] = 0
    bits = [clipped_bits(im, cov) for im, cov in zip(images, coverage)]
    assert [int(np.count_nonzero(b)) for b in bits] == [2, 1]
    k = Intrinsics(8.0, 8.0, 4.0, 3.0, 8, 6)
    rays = RaySet(images, [np.eye(4), np.eye(4)], [k, k], clipped=bits)
    assert rays.clipped_share() == 3 / 96
    # Kept sparse, read back whole, and a subset keeps its photos' own.
    assert np.array_equal(rays.clipped_channels(torch.arange(rays.num_pixels)).numpy(), np.concatenate(bits, None))
    assert np.array_equal(rays.subset([1]).clipped_channels(torch.arange(48)).numpy(), bits[1].reshape(-1))
    colour = PhotoColour(2)
    colour.gain = torch.tensor([[0.8, 1.0, 1.25], [1.1, 0.9, 1.0]], dtype=torch.float64)
    _, _, target = rays.batch(4096, "rays", 16, torch.Generator().manual_seed(5), colour=colour)
    photo = rays.pixel_rays(torch.randint(rays.num_pixels, (4096,), generator=torch.Generator().manual_seed(5)))[4]
    floors = target < 0
    # The floors are exactly the clipped channels the photos' own light filled.
    clipped_values = (photo * 255).round() >= 254
    white_put_in = (photo * 255).round().eq(255).all(1)
    assert bool((floors == (clipped_values & ~white_put_in[:, None])).all())
    assert int(floors.sum()) > 0 and int(white_put_in.sum()) > 0
    assert bool((target[~floors] >= 0).all()) and float((-target[floors]).min()) > 0.75  # 254 / 255 over a gain of 1.25
    without = RaySet(images, [np.eye(4), np.eye(4)], [k, k])
    assert without.clipped is None
    assert bool((without.batch(512, "rays", 16, torch.Generator().manual_seed(5))[2] >= 0).all())


def test_a_render_in_a_photos_colour_is_clamped_once_after_its_gains(tmp_path):
    """A clipped highlight trained as a floor renders above 1 in the common colour; in a photo's gain below 1 it must
    still show as bright as the field holds it, not as 1 times the gain."""
    root = make_scene(tmp_path, width=32)
    scene = read_json(root / "normalize" / "scene.json")
    model = SceneModel.create(scene, ModelOptions(sh_degree=0), 8)
    model.grid.density.fill_(50.0)
    model.grid.sh.fill_((1.2 - 0.5) / SH_C0)
    frame = scene["frames"][0]
    model.photo_gains = PhotoGains([frame["name"]], {frame["name"]: [0.8, 0.9, 1.0]})
    k = Intrinsics.from_frame(frame).scaled(0.5)
    with torch.no_grad():
        rgb = model.render_camera(np.asarray(frame["transform_matrix"]), k, photo=frame["name"])["rgb"]
        common = model.render_camera(np.asarray(frame["transform_matrix"]), k)
    solid = common["opacity"] > 0.999
    assert int(solid.sum()) > 10 and float(common["rgb"].max()) <= 1.0
    torch.testing.assert_close(rgb[solid], torch.tensor([0.96, 1.0, 1.0]).expand(int(solid.sum()), 3), atol=2e-3,
                               rtol=0)


def test_each_photos_gains_across_its_frame_are_found_and_spread_back_over_it():
    """Photos whose light differs across the frame (a shadow on one side, a glow on the other): the lattice of gains
    measured from a sparse lattice of pixels is the one that made them, clipped pixels say nothing of it, a cell no
    pixel sees keeps its photo's gain, and the lattice spread back over the frame takes the render to the photo."""
    gen = torch.Generator().manual_seed(3)
    photos, h, w, shape = 3, 120, 90, (4, 3)
    assert lattice_shape(torch.tensor([[h, w]] * photos), 4) == shape  # portrait: 4 rows, 3 columns in proportion
    field = 0.6 + 0.8 * torch.rand(photos, *shape, 3, generator=gen, dtype=torch.float64)
    spread = torch.stack([field_image(f.numpy(), h, w) for f in field]).reshape(photos, h, w, 3)
    rendered = 0.1 + 0.5 * torch.rand(photos, h, w, 3, generator=gen, dtype=torch.float64)
    photo = (spread * rendered).clamp(0, 1)
    clipped = photo >= 1
    photo[:, :24] = torch.where(torch.rand(photos, 24, w, 1, generator=gen) < 0.3, 1.0, photo[:, :24])  # blown out
    image, row, col = (t.reshape(-1) for t in torch.meshgrid(torch.arange(photos), torch.arange(h), torch.arange(w),
                                                             indexing="ij"))
    sizes = torch.tensor([[h, w]] * photos)
    gains = torch.ones(photos, 3, dtype=torch.float64)
    measured = gain_fields(image, row, col, sizes, rendered[image, row, col], photo[image, row, col], gains, shape)
    torch.testing.assert_close(measured, field, atol=0.02, rtol=0)
    back = torch.stack([field_image(f.numpy(), h, w) for f in measured]).reshape(photos, h, w, 3) * rendered
    good = ~clipped & (photo < 1)
    assert float((back - photo)[good].abs().max()) < 0.02
    # Photo 1's pixels in its right-hand column of cells alone are all blown out: those cells keep its own gain.
    photo[1, :, 2 * w // 3:] = 1.0
    gains[1] = torch.tensor([0.9, 1.0, 1.1], dtype=torch.float64)
    measured = gain_fields(image, row, col, sizes, rendered[image, row, col], photo[image, row, col], gains, shape)
    far = measured[1, :, 2]
    assert float((far.log() - gains[1].log()).abs().max()) < float((field[1, :, 2].log() - gains[1].log()).abs().max())
    torch.testing.assert_close(measured[0], field[0], atol=0.01, rtol=0)


def test_a_held_out_photo_takes_its_neighbours_lattices_where_they_follow_the_capture():
    """A shadow that moves across the frame as the camera turns: neighbours' lattices predict a photo's better than
    their gains, so a photo not fitted takes the lattice between them; lattices that say nothing of each other leave
    a held-out photo in its neighbours' gain."""
    order = [f"{i:03d}" for i in range(40)]
    held_out = order[5::10]
    rows, cols = np.meshgrid(np.linspace(0, 1, 4), np.linspace(0, 1, 3), indexing="ij")

    def shadow(i):
        centre = i / 39
        return np.repeat((1.0 - 0.4 * np.exp(-((cols - centre) ** 2 + (rows - 0.5) ** 2) / 0.1))[..., None], 3, axis=2)

    fitted = [name for name in order if name not in held_out]
    fields = {name: shadow(order.index(name)) for name in fitted}
    gains = {name: fields[name].mean(axis=(0, 1)) for name in fitted}
    moving = PhotoGains(order, gains, fields=fields)
    assert moving.fields_follow_order
    np.testing.assert_allclose(moving.field_of("014"), fields["014"])  # a measured photo keeps its own
    np.testing.assert_allclose(moving.field_of("015"), (fields["014"] + fields["016"]) / 2)
    assert moving.field_of("elsewhere") is None  # a camera of no photo: no lattice
    again = PhotoGains.from_record(moving.record())
    assert again.fields_follow_order and np.allclose(again.field_of("015"), moving.field_of("015"), atol=1e-4)
    assert PhotoGains(order, gains).field_of("015") is None  # one gain a photo measured: none
    # The exposure drifts along the capture, but the light across each frame is its own, unlike its neighbours'
    # (photos of a room taken from here and there): their gain is the better guess, and a held-out photo keeps it.
    rng = np.random.default_rng(0)
    drift = {name: np.full(3, 0.8 + 0.01 * order.index(name)) for name in fitted}
    own_light = {name: drift[name] * np.exp(0.2 * rng.standard_normal((4, 3, 3))) for name in fitted}
    scattered = PhotoGains(order, drift, fields=own_light)
    assert scattered.follows_order and not scattered.fields_follow_order
    assert scattered.field_of("015") is None
    np.testing.assert_allclose(scattered.of("015"), [0.95] * 3)
    np.testing.assert_allclose(scattered.field_of(fitted[3]), own_light[fitted[3]])  # a measured photo keeps its own
