"""Option names: one spelling per concept, old spellings kept as hidden aliases; ``pmcal`` sub-commands."""
from __future__ import annotations

import pytest

from markcal.pipeline.cli import build_parser, main

#: (command words, current spelling, old spelling, value given, destination, value expected from the old spelling)
ALIASES = [
    (["render", "om", "--out", "o"], "--pixel-size-um", "--pixel-um", "0.25", "pixel_size_um", 0.25),
    (["render", "selfcal", "--out", "o"], "--noise-um", "--noise-xy-um", "0.03", "noise_um", 0.03),
    (["render", "servo", "--out", "o"], "--noise-um", "--noise-nm", "7", "noise_um", 0.007),
    (["render", "servo-log", "--out", "o"], "--noise-um", "--noise-nm", "7", "noise_um", 0.007),
    (["render", "servo-log", "--out", "o"], "--settle-band-um", "--band-um", "3", "settle_band_um", 3.0),
    (["render", "grid", "--out", "o"], "--noise-um", "--noise-mm", "0.01", "noise_um", 10.0),
    (["render", "grid", "--out", "o"], "--missing-marks", "--missing", "3", "missing_marks", 3),
    (["render", "servo-log", "--out", "o"], "--sample-period-ms", "--ts-ms", "0.2", "sample_period_ms", 0.2),
    (["path", "job.csv", "--out", "o"], "--chord-tolerance-mm", "--tolerance-mm", "0.02", "tolerance_mm", 0.02),
]


@pytest.mark.parametrize("words, new, old, value, dest, expected", ALIASES)
def test_old_and_new_spellings_give_the_same_value(words, new, old, value, dest, expected):
    p = build_parser()
    a_new = p.parse_args([*words, new, str(expected)])
    a_old = p.parse_args([*words, old, value])
    assert getattr(a_new, dest) == pytest.approx(expected, rel=1e-12)
    assert getattr(a_old, dest) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("words, new, old, value, dest, expected", ALIASES)
def test_help_lists_the_new_spelling_only(words, new, old, value, dest, expected, capsys):
    with pytest.raises(SystemExit, match="0"):
        build_parser().parse_args([*words[:2 if words[0] == "render" else 1], "--help"])
    out = capsys.readouterr().out
    assert new in out
    assert old not in out.replace(new, "")


def test_default_without_either_spelling():
    a = build_parser().parse_args(["render", "servo", "--out", "o"])
    assert a.noise_um == pytest.approx(0.005)
    a = build_parser().parse_args(["render", "grid", "--out", "o"])
    assert a.noise_um == pytest.approx(20.0)


def test_pmcal_subcommands_and_the_old_form():
    p = build_parser()
    old = p.parse_args(["pmcal", "sess", "--out", "o", "--method", "lsq"])
    new = p.parse_args(["pmcal", "calibrate", "sess", "--out", "o", "--method", "lsq"])
    first_option = p.parse_args(["pmcal", "--out", "o", "sess"])
    for a in (old, new, first_option):
        assert (a.pmcal_command, a.session, a.out) == ("calibrate", "sess", "o")
    assert old.method == new.method == "lsq"
    c = p.parse_args(["pmcal", "command", "cal.json", "t.csv", "--depth-um", "2", "-o", "c.csv"])
    assert (c.pmcal_command, c.calibration, c.targets, c.depth_um, c.out) == ("command", "cal.json", "t.csv", 2.0, "c.csv")
    assert c.func.__name__ == "cmd_pmcal_command" and old.func.__name__ == "cmd_pmcal"


def test_pmcal_help_names_both_subcommands(capsys):
    with pytest.raises(SystemExit, match="0"):
        build_parser().parse_args(["pmcal", "--help"])
    out = capsys.readouterr().out
    assert "calibrate" in out and "command" in out


def test_pmcal_command_refuses_extra_words(capsys):
    with pytest.raises(SystemExit, match="1"):
        main(["pmcal", "command", "a.json", "b.csv", "c.csv", "--depth-um", "1", "--out", "x.csv"])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: ") and "unrecognized arguments: c.csv" in err[0]


def test_usage_mistakes_are_one_line_exit_1(capsys):
    for argv in (["scan"], ["render", "grid", "--rows", "many", "--out", "o"], ["nosuchcommand"]):
        with pytest.raises(SystemExit, match="1"):
            main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("markcal: error: "), (argv, err)


def test_usage_mistake_prints_through_the_one_error_printer(capsys):
    """A bad command line is printed as every other error: no ANSI codes, no bidirectional overrides."""
    with pytest.raises(SystemExit, match="1"):
        main(["pmcal", "command", "a.json", "b.csv", "\u202e\x1b[31mc.csv", "--depth-um", "1", "--out", "x.csv"])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unrecognized arguments: \\u202ec.csv (see markcal" in err[0], err
    assert "\u202e" not in err[0] and "\x1b" not in err[0]


def test_a_known_command_imports_only_its_module_and_parses_as_the_full_parser():
    import sys
    from markcal.pipeline.cli import COMMAND_OWNERS
    full = build_parser()
    commands = set(full._subparsers._group_actions[0].choices)
    assert set(COMMAND_OWNERS) == commands - {"render"}            # every command has its module
    for cmd, module in COMMAND_OWNERS.items():
        lazy = build_parser([cmd, "x"])
        sub = lazy._subparsers._group_actions[0].choices
        assert cmd in sub and set(sub) < commands                  # the command, and not every module's
        assert sub[cmd].format_help() == full._subparsers._group_actions[0].choices[cmd].format_help()
        assert module in sys.modules
    with pytest.raises(SystemExit, match="1"):                     # an unknown command: the usual one-line error
        build_parser(["scann"]).parse_args(["scann"])
