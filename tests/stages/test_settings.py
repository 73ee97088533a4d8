"""Each stage's settings take their libraries' options whole: the options check themselves (a bad value is one line
naming the key), and a stage's settings check runs every options check it extends, then its own."""
from __future__ import annotations

import pytest

from pipeline import config
from pipeline.stage import STAGE_ORDER, StageGraph
from plenoxels.core.errors import UserError
from stages.framing.options import SceneOptions
from stages.sfm.options import SfmOptions


def one_line_error(build) -> str:
    with pytest.raises(UserError) as info:
        build()
    message = str(info.value)
    assert "\n" not in message, message
    return message


@pytest.mark.parametrize("options, key", [
    (SceneOptions(holdout_every=1), "normalize.holdout_every"),
    (SceneOptions(train_every=0), "normalize.train_every"),
    (SceneOptions(margin=1.5), "normalize.margin"),
    (SceneOptions(borderline_deg=40.0), "normalize.borderline_deg"),
    (SceneOptions(beyond_factor=1.0), "normalize.beyond_factor"),
    (SfmOptions(max_features=10), "poses.max_features"),
    (SfmOptions(feature_max_side=10), "poses.feature_max_side"),
    (SfmOptions(sensor_width_mm=-1.0), "poses.sensor_width_mm"),
    (SfmOptions(threads=-1), "poses.threads"),
])
def test_each_options_check_rejects_a_bad_value_in_one_line_naming_the_key(options, key):
    assert one_line_error(options.check).startswith(key + " ")
    options.__class__().check()


@pytest.mark.parametrize("stage, key, bad", [
    ("fit", "step_size", 0.0),            # MarchOptions
    ("fit", "sh_degree", 5),              # ModelOptions
    ("fit", "tv_background", -1.0),       # ModelOptions
    ("fit", "lr_background", 0.0),        # TrainOptions
    ("fit", "voxel_budget", 5),           # TrainOptions
    ("fit", "image_scale", 2.0),          # the fit stage's own
    ("export", "level_share", 1.0),       # MeshOptions
    ("export", "texture_views", 0),       # the export stage's own
    ("normalize", "forward_max_cone_deg", 95.0),  # SceneOptions
    ("poses", "exhaustive_max_images", 1),        # SfmOptions
    ("poses", "min_registered_share", 0.0),       # the poses stage's own
    ("ingest", "min_images", 2),
    ("evaluate", "video_side", 8),
])
def test_a_bad_setting_is_one_line_naming_the_key(stage, key, bad):
    settings = StageGraph().declaration(stage).Settings
    assert one_line_error(lambda: config.build(settings, stage, {key: bad})).startswith(f"{stage}.{key} ")


@pytest.mark.parametrize("stage", STAGE_ORDER)
def test_a_stages_settings_check_runs_the_check_of_every_options_class_it_extends(stage, monkeypatch):
    settings = StageGraph().declaration(stage).Settings
    extended = [cls for cls in settings.__mro__[1:] if "check" in vars(cls)]
    ran = []
    for cls in extended:
        original = vars(cls)["check"]
        monkeypatch.setattr(cls, "check", lambda self, *args, _cls=cls, _check=original: ran.append(_cls)
                            or _check(self, *args))
    config.build(settings, stage, {})
    assert sorted(c.__name__ for c in ran) == sorted(c.__name__ for c in extended)
