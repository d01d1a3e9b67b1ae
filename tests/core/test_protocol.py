"""The pure protocol layer: grammar, tags, quoting, reply framing, option binding and its errors."""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import Field

from rvs_server.config import CommandConfig, Point, Range, SafeName, bind_tokens, build_config
from rvs_server.protocol import (
    BadRequest,
    RvsError,
    build_line,
    format_err,
    format_event,
    format_ok,
    format_pairs,
    format_progress,
    is_ignored,
    parse_line,
    parse_pairs,
    parse_reply,
    split_tag,
)
from rvs_server.transports.tcp import TelnetFilter


class Demo(CommandConfig):
    pan: float | None = Field(None, ge=-159.0, le=159.0)
    speed: float = Field(20.0, gt=0, le=300)
    relative: bool = False
    area: Range | None = None
    goal: Point | None = None
    output: SafeName | None = None
    seconds: float = 1.0


def bind(line: str, positionals=()) -> CommandConfig:
    parsed = parse_line(line)
    return build_config(parsed.command, Demo, {}, bind_tokens(parsed.command, parsed.tokens, Demo, positionals))


def test_line_grammar_tag_command_options():
    parsed = parse_line('@g-1.a move-PTU --pan 30 --tilt=-20 "quoted value" --relative')
    assert parsed.tag == "g-1.a"
    assert parsed.command == "move-ptu"
    assert parsed.tokens == ("--pan", "30", "--tilt=-20", "quoted value", "--relative")


def test_tags_must_be_well_formed():
    assert split_tag("@ok_tag.1 status") == ("ok_tag.1", "status")
    assert split_tag("@" + "a" * 33 + " status")[0] is None
    assert split_tag("@bad! status")[0] is None
    with pytest.raises(BadRequest, match="not 1 to 32 characters"):
        parse_line("@bad! status")
    with pytest.raises(BadRequest, match="command is missing"):
        parse_line("@t1")


def test_blank_and_comment_lines_are_ignored():
    assert is_ignored("")
    assert is_ignored("   \t")
    assert is_ignored("# a comment")
    assert is_ignored("   # indented comment")
    assert not is_ignored("status # not a comment")


def test_unbalanced_quotes_are_a_bad_request():
    with pytest.raises(BadRequest, match="cannot split"):
        parse_line('move-ptu --pan "30')


def test_negative_values_and_flags_bind_by_type():
    cfg = bind("move-ptu --pan -20 --relative")
    assert cfg.pan == -20.0 and cfg.relative is True
    assert bind("move-ptu --no-relative").relative is False
    assert bind("move-ptu --pan=-5.5").pan == -5.5


def test_ranges_points_and_names():
    cfg = bind("x --area -30:40 --goal 3.5,-2 --output run_01.a")
    assert cfg.area == (-30.0, 40.0) and cfg.goal == (3.5, -2.0) and cfg.output == "run_01.a"


@pytest.mark.parametrize("line, words", [
    ("x --pan 200", ["--pan", "200", "-159..159"]),
    ("x --speed 0", ["--speed", "> 0"]),
    ("x --speed fast", ["--speed", "'fast'"]),
    ("x --area 5:1", ["--area", "greater than its end"]),
    ("x --goal 1", ["--goal", "X,Y"]),
    ("x --output ../etc", ["--output", "safe name"]),
    ("x --output .hidden", ["--output", "safe name"]),
    ("x --spede 3", ["unknown option --spede", "did you mean --speed"]),
    ("x --pan", ["--pan needs a value"]),
    ("x --pan 1 --pan 2", ["--pan given twice"]),
    ("x --no-pan", ["unknown option --no-pan"]),
    ("x stray", ["unexpected argument 'stray'"]),
])
def test_bad_options_name_the_option_and_the_allowed_values(line, words):
    with pytest.raises(BadRequest) as info:
        bind(line)
    for word in words:
        assert word in info.value.message
    assert info.value.code == 400 and info.value.reason == "bad-request"


def test_positionals_bind_to_named_fields():
    assert bind("sleep 2.5", positionals=("seconds",)).seconds == 2.5


def test_reply_framing_round_trips():
    line = format_ok("7", {"mode": "standby", "message": 'two words "quoted"\\', "pan": 30.0, "empty": ""})
    assert line.startswith("7 OK mode=standby ")
    reply = parse_reply(line)
    assert reply.kind == "ok" and reply.tag == "7"
    assert reply.data == {"mode": "standby", "message": 'two words "quoted"\\', "pan": "30", "empty": ""}
    err = parse_reply(format_err("a", 409, "busy", "job 3 (move-ptu)\nis running"))
    assert (err.kind, err.code, err.reason, err.message) == ("err", 409, "busy", "job 3 (move-ptu) is running")
    prog = parse_reply(format_progress("a", 42.6, "moving"))
    assert (prog.kind, prog.percent, prog.message) == ("progress", 43, "moving")
    event = parse_reply(format_event("mode", {"mode": "busy"}))
    assert (event.kind, event.topic, event.data) == ("event", "mode", {"mode": "busy"})


def test_build_line_is_parsed_back_to_the_same_tokens():
    line = build_line("grab-tof", options={"output": "a b", "frames": 3, "relative": True, "pan": None}, tag="q")
    parsed = parse_line(line)
    assert parsed.tag == "q" and parsed.tokens == ("--output", "a b", "--frames", "3", "--relative")


def test_build_line_names_options_as_the_server_binds_them():
    """Field names as the commands' Config classes have them (`from_`, `no_sun`) give the flags the
    server's parser expects, so `build_line` and `help` can never disagree."""
    from rvs_server.app import all_modules
    from rvs_server.config import bind_tokens, option_name
    checked = 0
    for module in all_modules():
        for spec in module.commands:
            for name, field in spec.config.model_fields.items():
                if name in spec.positionals or field.annotation is bool:
                    continue
                tokens = parse_line(build_line(spec.name, options={name: "x"})).tokens
                assert tokens[0] == option_name(name)  # the flag `help` shows
                assert name in bind_tokens(spec.name, tokens, spec.config, spec.positionals), (spec.name, name)
                checked += 1
    assert checked > 50


def test_telnet_negotiation_is_removed_across_chunks():
    filt = TelnetFilter()
    stream = b"\xff\xfb\x01sta" + b"\xff\xfa\x18\x00xterm\xff\xf0" + b"tus\r\n"
    out = b"".join(filt.feed(stream[i:i + 3]) for i in range(0, len(stream), 3))
    assert out == b"status\r\n"


def test_telnet_option_requests_are_refused_and_cr_nul_ends_a_line():
    """What `telnet` sends after `mode character` (DO SGA, DO ECHO, then Enter as CR NUL) and after
    `open HOST -PORT` (its full negotiation): each DO is answered WONT, each WILL DONT, never a WONT or
    DONT (RFC 854: no loops), and CR NUL ends the line, even split across chunks."""
    filt = TelnetFilter()
    assert filt.feed(b"\xff\xfd\x03\xff\xfd\x01status\r") == b"status\r"
    assert filt.feed(b"\x00") == b"\n"
    assert bytes(filt.answers) == b"\xff\xfc\x03\xff\xfc\x01"
    filt.answers.clear()
    stream = b"\xff\xfd&\xff\xfb&\xff\xfd\x03\xff\xfb\x18\xff\xfc\x01\xff\xfe\x05ver\r\x00sion\r\n"
    out = b"".join(filt.feed(stream[i:i + 2]) for i in range(0, len(stream), 2))
    assert out == b"ver\r\nsion\r\n"
    assert bytes(filt.answers) == b"\xff\xfc&\xff\xfe&\xff\xfc\x03\xff\xfe\x18"
    assert TelnetFilter().feed(b"a\x00b\n") == b"a\x00b\n"  # a NUL not after a CR is data


def test_every_error_reason_has_its_code():
    assert RvsError("x", reason="device").code == 503
    assert RvsError("x", reason="sleeping").code == 423
    with pytest.raises(ValueError):
        RvsError("x", reason="nonsense")


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=200))
def test_parser_never_raises_anything_but_bad_request(text):
    try:
        parsed = parse_line(text)
    except BadRequest:
        return
    assert parsed.command and not parsed.command.startswith("-")


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.from_regex(r"[a-z][a-z0-9_.]{0,10}", fullmatch=True), st.text(max_size=40), max_size=6))
def test_pairs_round_trip_for_any_text(data):
    text = format_pairs(data)
    assert "\n" not in text and "\r" not in text
    assert parse_pairs(text) == data
