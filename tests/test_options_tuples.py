"""Options typed tuple[str, ...]: a tuple of strings, with choices checked per element."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from autonomy.options import OptionError, option, validate
from companion.config import _coerce


@dataclass(frozen=True)
class Listed:
    names: tuple[str, ...] = option(("a", "b"), choices=("a", "b", "c"), doc="some names")
    free: tuple[str, ...] = option((), doc="any strings")

    def __post_init__(self) -> None:
        validate(self)


def test_a_tuple_of_allowed_strings_is_accepted_in_any_order():
    assert Listed().names == ("a", "b")
    assert Listed(names=("c", "a"), free=("x", "y")).free == ("x", "y")


def test_choices_apply_to_each_element_and_name_the_bad_one():
    with pytest.raises(OptionError, match=r"names: must be one of a, b, c; got 'z'"):
        Listed(names=("a", "z"))


@pytest.mark.parametrize("value", [["a"], "a", ("a", 1), None])
def test_anything_but_a_tuple_of_strings_is_refused(value):
    with pytest.raises(OptionError, match="names: must be a list of strings"):
        Listed(names=value)


def test_config_turns_a_toml_list_into_a_tuple_only_for_tuple_fields():
    assert _coerce(["a", "b"], tuple[str, ...]) == ("a", "b")
    assert _coerce(["a"], str) == ["a"]
    assert _coerce(3, float) == 3.0
