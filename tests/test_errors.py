"""The one-line promise of every user-facing error, whatever its message quotes."""

from __future__ import annotations

import pytest

from latentdrive.config import ConfigError, validate
from latentdrive.errors import LatentDriveError, first_line, printable
from latentdrive.rl.config import PolicyTrainConfig


def test_printable_escapes_control_characters_only() -> None:
    assert printable("runs.d8: ok") == "runs.d8: ok"
    assert printable("a\nb\tc\x00é") == "a\\nb\\tc\\x00é"


def test_an_error_message_is_one_line_whatever_it_quotes() -> None:
    assert str(LatentDriveError("key 'a\r\nb' unknown")) == "key 'a\\r\\nb' unknown"
    assert str(ConfigError("x\ny")) == "x\\ny"


def test_a_config_key_with_a_line_break_is_named_on_one_line() -> None:
    with pytest.raises(ConfigError) as info:
        validate(PolicyTrainConfig, {"bad\nkey": 1})
    assert str(info.value) == "invalid config: bad\\nkey: unknown key"


def test_first_line_quotes_a_library_error_briefly() -> None:
    assert first_line(ValueError("first\nsecond")) == "first"
    assert first_line(KeyError()) == "KeyError"
