"""Config: per-stage parameter objects, the flat keys users set, presets, validation."""

import dataclasses
import json
import math

import numpy as np
import pytest

from arlight.pipeline.config import (
    FLAT_KEYS,
    Config,
    EstimationParams,
    FilterParams,
    Preset,
    SegmentFeatures,
    TemporalParams,
    TransferParams,
    VisibilityRamp,
    VolumeParams,
)


class TestFlatKeys:
    def test_presets(self):
        # `full` is the defaults with compact sources on (decision 0061) and its SH fitted
        # near the look-at point, the sources searched over the whole view (decision 0064);
        # `fast` has them too (decisions 0062-0064), `mobile` not
        assert Config().replace(
            compact_sources=1,
            fit_radius_m=1.0,
            fit_radius_sources_everywhere=True,
            fit_radius_sources_samples=10000,
        ) == Config.from_preset("full")
        fast = Config.from_preset("fast").estimation
        assert (fast.fit_radius_m, fast.fit_radius_sources_everywhere) == (1.0, True)
        assert Config.from_preset("fast").estimation.compact_sources == 1
        assert Config.from_preset("mobile").estimation.compact_sources == 0
        assert Config.from_preset("fast").transfer.rt_subsample == 4
        mobile = Config.from_preset("mobile")
        assert mobile.preset is Preset.MOBILE
        assert (
            mobile.volume.volume_resolution,
            mobile.filter.denoise,
            mobile.transfer.rt_subsample,
        ) == (64, False, 4)

    def test_every_stage_field_has_one_flat_key(self):
        for stage in ("volume", "aux", "filter", "transfer", "estimation", "temporal"):
            for f in dataclasses.fields(getattr(Config(), stage)):
                assert FLAT_KEYS[f.name] == (stage, f.name)

    def test_overrides_reach_their_stage(self):
        c = Config.from_preset(
            "fast",
            rt_directions=128,
            visibility=False,
            seed=3,
            merge_window=10,
            regularization=1e-3,
        )
        assert c.transfer.rt_directions == 128 and not c.transfer.visibility
        assert c.transfer.rt_subsample == 4  # the preset's own value kept
        assert c.seed == 3 and c.filter.merge_window == 10
        assert c.estimation.regularization == 1e-3
        d = c.replace(rt_directions=32)
        assert d.transfer.rt_directions == 32 and d.filter == c.filter
        assert c.transfer.rt_directions == 128  # frozen: replace makes a copy

    def test_unknown_key_lists_the_valid_ones(self):
        with pytest.raises(ValueError, match="no_such_key.*valid keys:.*rt_directions"):
            Config.from_preset("full", no_such_key=1)
        with pytest.raises(ValueError, match="no_such_key"):
            Config().replace(no_such_key=1)

    def test_unknown_preset(self):
        with pytest.raises(ValueError, match="preset"):
            Config.from_preset("ultra")

    def test_change_reset_in_radians_with_a_degrees_alias(self):
        assert Config().temporal.change_reset_rad == math.radians(35.0)
        c = Config.from_preset("full", change_reset_deg=20)
        assert c.temporal.change_reset_rad == math.radians(20.0)
        with pytest.raises(ValueError, match="not both"):
            Config.from_preset("full", change_reset_deg=20, change_reset_rad=0.3)

    def test_string_options_become_enums(self):
        c = Config.from_preset("full", rt_visibility_ramp="half", segment_features="chroma")
        assert c.transfer.rt_visibility_ramp is VisibilityRamp.HALF
        assert c.estimation.segment_features is SegmentFeatures.CHROMA
        assert c.estimation.segment_features == "chroma"  # (str, Enum)

    def test_flat_record_is_json(self):
        flat = Config.from_preset("fast").flat()
        assert json.loads(json.dumps(flat)) == flat
        assert flat["preset"] == "fast" and flat["rt_visibility_ramp"] == "paper"

    def test_flat_key_types_for_the_command_line(self):
        types = Config.flat_key_types()
        assert types["rt_directions"] is int and types["visibility"] is bool
        assert types["regularization"] is float and types["rt_visibility_ramp"] is str
        assert types["change_reset_deg"] is float and types["device"] is str


class TestValidation:
    @pytest.mark.parametrize(
        "key, value, match",
        [
            ("rt_directions", 2, r"rt_directions must be >= 4 \(--set rt_directions=N\), got 2"),
            ("sh_bands", 13, r"sh_bands must be in 1\.\.12"),
            ("sh_bands", "many", "sh_bands must be an integer"),
            ("rt_steps", 1.5, "rt_steps must be an integer"),
            ("visibility", 1, "visibility must be true or false"),
            ("rt_radius_m", 0.0, "rt_radius_m must be > 0"),
            ("rt_visibility_ramp", "steep", "rt_visibility_ramp must be one of paper|half"),
            ("segment_features", "hue", "segment_features must be one of invariant|chroma"),
            ("merge_window", 65, r"merge_window must be in 1\.\.64"),
            ("merge_depth_threshold_m", float("nan"), "merge_depth_threshold_m must be finite"),
            ("volume_resolution", 4, "volume_resolution must be >= 8"),
            ("depth_max_m", 0.05, "depth_max_m must be >"),
            ("aux_update_interval", 0, "aux_update_interval must be >= 1"),
            ("light_max_samples", 10, r"light_max_samples must be >= min_samples \(200\)"),
            ("horizon_ground_albedo", 1.5, "horizon_ground_albedo must be <= 1"),
            ("temporal_half_life_frames", -1.0, "temporal_half_life_frames must be >= 0"),
            ("change_reset_rad", 4.0, "change_reset_rad must be <="),
            ("device", "GPU", "device must be 'CPU:0' or 'CUDA:0'"),
            ("seed", -1, "seed must be >= 0"),
        ],
    )
    def test_bad_values_name_the_key(self, key, value, match):
        with pytest.raises(ValueError, match=match):
            Config.from_preset("full", **{key: value})

    def test_stage_objects_check_themselves(self):
        with pytest.raises(ValueError, match="rt_directions"):
            TransferParams(rt_directions=0)
        with pytest.raises(ValueError, match="smooth_subsample"):
            FilterParams(smooth_subsample=0)
        with pytest.raises(ValueError, match="min_samples"):
            EstimationParams(min_samples=0)
        with pytest.raises(ValueError, match="block_count"):
            VolumeParams(block_count=0)
        with pytest.raises(ValueError, match="change_reset_rad"):
            TemporalParams(change_reset_rad=0.0)

    def test_numbers_of_another_type_are_normalised(self):
        c = Config.from_preset("full", regularization=1, rt_directions=np.int64(32))
        assert type(c.estimation.regularization) is float
        assert type(c.transfer.rt_directions) is int
