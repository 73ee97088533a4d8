"""The model's options check themselves: each class's check() turns a bad value into one line naming the key, and an
option shared by the fit's settings and a render is declared once."""
from __future__ import annotations

import dataclasses

import pytest

from plenoxels.core.errors import UserError
from plenoxels.core.options import MarchOptions, MeshOptions, ModelOptions, TrainOptions
from plenoxels.core.render import RenderOptions


def one_line_error(options, section: str | None = None) -> str:
    with pytest.raises(UserError) as info:
        options.check() if section is None else options.check(section)
    message = str(info.value)
    assert "\n" not in message, message
    return message


@pytest.mark.parametrize("options, key", [
    (MarchOptions(step_size=0.0), "fit.step_size"),
    (MarchOptions(stop_transmittance=1.0), "fit.stop_transmittance"),
    (ModelOptions(step_size=-1.0), "fit.step_size"),
    (ModelOptions(sh_degree=4), "fit.sh_degree"),
    (ModelOptions(background_color=[1.0, 1.0]), "fit.background_color"),
    (ModelOptions(near_share=1.0), "fit.near_share"),
    (ModelOptions(background_width=2), "fit.background_width"),
    (ModelOptions(tv_background=-1.0), "fit.tv_background"),
    (TrainOptions(resolutions=[128, 64], steps=[1, 1]), "fit.resolutions"),
    (TrainOptions(steps=[100]), "fit.steps"),
    (TrainOptions(first_level_scale=0.0), "fit.first_level_scale"),
    (TrainOptions(lr_sh_final=0.0), "fit.lr_sh_final"),
    (TrainOptions(rmsprop_beta=1.0), "fit.rmsprop_beta"),
    (TrainOptions(lr_background=0.0), "fit.lr_background"),
    (TrainOptions(prune_ray_scale=1.5), "fit.prune_ray_scale"),
    (TrainOptions(voxel_budget=10), "fit.voxel_budget"),
    (MeshOptions(resolution=4), "export.resolution"),
    (MeshOptions(level=0.0), "export.level"),
    (MeshOptions(level_share=1.0), "export.level_share"),
    (MeshOptions(max_faces=2), "export.max_faces"),
    (MeshOptions(fill_voxels=-1), "export.fill_voxels"),
    (MeshOptions(point_opacity=0.0), "export.point_opacity"),
    (RenderOptions(step_size=0.0), "fit.step_size"),
    (RenderOptions(sigma_threshold=-1.0), "sigma_threshold"),
    (RenderOptions(max_samples_per_ray=0), "max_samples_per_ray"),
])
def test_each_options_check_rejects_a_bad_value_in_one_line_naming_the_key(options, key):
    assert key in one_line_error(options)


@pytest.mark.parametrize("options", [MarchOptions(), ModelOptions(), TrainOptions(), MeshOptions(), RenderOptions()])
def test_the_defaults_pass_their_own_check(options):
    options.check()


def test_a_check_names_the_key_under_the_section_that_set_it():
    assert one_line_error(TrainOptions(batch_size=0), "trial").startswith("trial.batch_size ")
    assert one_line_error(ModelOptions(stop_transmittance=-0.1), "trial").startswith("trial.stop_transmittance ")


def test_a_render_marches_with_the_fits_options_declared_once():
    """The step size and stopping threshold a fit sets are the ones a render defaults to: one declaration, one
    default, one check, shared by ModelOptions and RenderOptions."""
    march = {f.name for f in dataclasses.fields(MarchOptions)}
    for cls in (ModelOptions, RenderOptions):
        declared_again = march & set(vars(cls).get("__annotations__", {}))
        assert not declared_again, f"{cls.__name__} declares {sorted(declared_again)} again"
        assert {name: getattr(cls(), name) for name in march} == {name: getattr(MarchOptions(), name) for name in march}
    assert RenderOptions(step_size=0.25).check().step_size == 0.25
