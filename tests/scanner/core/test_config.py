from dataclasses import dataclass, field

import pytest

from scanner.core.config import ConfigError, load_config


@dataclass(frozen=True)
class Limits:
    tolerance_mm: float
    count: int = 3


@dataclass(frozen=True)
class Example:
    name: str
    limits: Limits
    sizes: tuple[float, ...] = ()
    tags: list[str] = field(default_factory=list)
    mode: str = "fast"

    def __post_init__(self) -> None:
        if self.mode not in ("fast", "precise"):
            raise ValueError(f"mode: expected 'fast' or 'precise', got {self.mode!r}")


def write(tmp_path, text):
    path = tmp_path / "example.toml"
    path.write_text(text)
    return path


def test_valid_config_is_converted_by_type(tmp_path):
    cfg = load_config(
        Example, write(tmp_path, 'name = "a"\nsizes = [1, 2.5]\n[limits]\ntolerance_mm = 1\n')
    )
    assert cfg == Example("a", Limits(1.0, 3), (1.0, 2.5))
    assert isinstance(cfg.limits.tolerance_mm, float)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            'name = "a"\n[limits]\ntolerance_mm = "x"\n',
            "line 3: limits.tolerance_mm: expected a number, got 'x'",
        ),
        ('name = "a"\n[limits]\ntolerance_mm = 1\ncoutn = 2\n', "limits.coutn: unknown key"),
        ("[limits]\ntolerance_mm = 1\n", "name: missing required key"),
        (
            'name = "a"\nmode = "slow"\n[limits]\ntolerance_mm = 1\n',
            "mode: expected 'fast' or 'precise'",
        ),
        ('name = "a"\n[limits\n', "not valid TOML"),
        (
            'name = "a"\n[limits]\ntolerance_mm = inf\n',
            "line 3: limits.tolerance_mm: expected a finite number, got inf",
        ),
        ('name = "a"\n[limits]\ntolerance_mm = nan\n', "expected a finite number, got nan"),
    ],
)
def test_bad_config_names_file_line_and_key(tmp_path, text, message):
    with pytest.raises(ConfigError) as err:
        load_config(Example, write(tmp_path, text))
    assert "example.toml" in str(err.value)
    assert message in str(err.value)


def test_a_path_with_a_folder_is_never_replaced_by_a_shipped_namesake(tmp_path):
    from scanner.core.config import resolve_config
    from scanner.core.fileio import InputError

    assert resolve_config("paper_sweep", "plans").is_file()  # a bare name: the shipped plan
    with pytest.raises(InputError, match="config not found"):
        resolve_config(tmp_path / "nowhere" / "paper_sweep.toml", "plans")
    with pytest.raises(InputError, match="config not found"):
        resolve_config("/etc/nowhere/plc.toml")
