"""One parameter system (``topoloc._params.Configurable``) for recognisers, vocabularies, features and models."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from topoloc.coocmap.model import CoocModel
from topoloc.errors import TopolocError
from topoloc.features import FeatureConfig
from topoloc.methods.base import parse_param
from topoloc.methods.cooc_map import CoocMap
from topoloc.synth import RouteConfig
from topoloc.vocabulary import Vocabulary


def test_the_old_cooc_map_name_points_to_the_new_one() -> None:
    for call in (lambda: CoocMap(max_features=5),  # type: ignore[call-arg]
                 lambda: CoocMap().set_params(max_features=5),
                 lambda: parse_param(CoocMap, "max_features", "5")):
        with pytest.raises(TopolocError, match=r"'max_features': it is now called 'max_words_per_image'$"):
            call()
    assert CoocMap(max_words_per_image=5).get_params()["max_words_per_image"] == 5


def test_saved_params_under_the_old_name_load_with_their_value() -> None:
    old = {"grid_x": 12, "max_features": 300, "top_k": 10}
    assert CoocMap.upgrade_params(old) == {"grid_x": 12, "max_words_per_image": 300, "top_k": 10}
    assert CoocMap.upgrade_params({"max_features": 1, "max_words_per_image": 2}) == {"max_words_per_image": 2}


@pytest.mark.parametrize(("make", "message"), [
    (lambda: Vocabulary(n_words=1), "vocabulary: n_words must be an integer >= 2, got 1"),
    (lambda: FeatureConfig(max_side=-1), "features: max_side must be an integer >= 0, got -1"),
    (lambda: CoocModel(n_locations=1, n_words=4, position_bits=17),
     "coocmap: position_bits must be an integer in [1, 16], got 17"),
    (lambda: RouteConfig(sidewalk_m=5.0), "synthetic route: sidewalk_m must be < street_width_m / 2 - 1 = 4, got 5.0"),
])
def test_every_owner_reports_a_bad_parameter_alike(make: object, message: str) -> None:
    with pytest.raises(TopolocError) as err:
        make()  # type: ignore[operator]
    assert str(err.value) == message


def test_numpy_scalars_are_numbers_and_frozen_settings_stay_frozen() -> None:
    assert CoocModel(n_locations=np.int64(3), n_words=np.int32(4)).n_words == 4  # type: ignore[arg-type]
    cfg = FeatureConfig()
    with pytest.raises(TopolocError, match=r"dataclasses\.replace"):
        cfg.set_params(max_features=10)
    assert dataclasses.replace(cfg, max_features=10).max_features == 10


def test_a_parameter_error_names_other_parameters_by_whatever_names_the_reader_uses() -> None:
    """The library names parameters, the command line their flags (issue #49): one message, refs rendered."""
    import pickle

    from topoloc.errors import ParameterError

    exc = ParameterError("html", "draws the whole S: leave out {top_k}, or {html}", ("top_k", "html"))
    assert str(exc) == "html draws the whole S: leave out top_k, or html"
    assert exc.render(lambda p: "--" + p.replace("_", "-")) == "draws the whole S: leave out --top-k, or --html"
    owned = ParameterError("ds", "must be an integer >= 0, got -1", owner="seqslam")
    assert str(owned) == "seqslam: ds must be an integer >= 0, got -1"
    for e in (exc, owned):  # a Dask task's error travels back pickled, whole
        back = pickle.loads(pickle.dumps(e))
        assert (type(back), str(back), back.refs, back.owner) == (type(e), str(e), e.refs, e.owner)


def test_a_constraint_error_is_a_parameter_error_with_its_owner() -> None:
    from topoloc.errors import ParameterError
    from topoloc.features import FeatureConfig

    with pytest.raises(ParameterError) as info:
        FeatureConfig(max_features=0)
    assert (info.value.param, info.value.owner) == ("max_features", "features")
    assert str(info.value) == "features: max_features must be an integer >= 1, got 0"
