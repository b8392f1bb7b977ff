"""Local mode's Host and Origin check (api/host_guard.py) in process: what a tokenless server answers, what the
settings accept, and where it may listen. The attacks over a real server: tests/test_hostile_requests.py."""
from __future__ import annotations

import pytest

from shadowopt.api.host_guard import host_name, refusal
from shadowopt.api.server import check_host
from shadowopt.api.settings import Settings, SettingsError, load_settings


def scope(host: str | None, origin: str | None = None) -> dict:
    headers = [(b"host", host.encode())] if host is not None else []
    if origin is not None:
        headers.append((b"origin", origin.encode()))
    return {"type": "http", "scheme": "http", "headers": headers}


@pytest.mark.parametrize("value, name", [("localhost:8000", "localhost"), ("[::1]:8000", "::1"), ("[::1]", "::1"),
                                         ("127.0.0.1", "127.0.0.1"), ("Shadow.LAN:80", "shadow.lan"),
                                         ("a:b", None), ("[::1", None), ("[::1]x", None), ("", None)])
def test_host_name_drops_the_port_and_refuses_what_does_not_parse(value, name):
    assert host_name(value) == name


def test_a_tokenless_server_answers_local_names_and_its_own_pages_only():
    s = Settings()
    for host in ("localhost:8000", "127.0.0.1:8000", "[::1]:8000", "127.0.0.2", None):
        assert refusal(scope(host), s) is None, host
    assert refusal(scope("127.0.0.1:8000", "http://127.0.0.1:8000"), s) is None  # /inspect's own requests
    status, code, message, field = refusal(scope("attacker.example:8000"), s)
    assert (status, code, field) == (400, "host_not_allowed", "Host") and "DNS rebinding" in message
    status, code, message, field = refusal(scope("127.0.0.1:8000", "https://attacker.example"), s)
    assert (status, code, field) == (403, "origin_not_allowed", "Origin") and "cross-site" in message
    assert refusal(scope("localhost:8000", "http://localhost:9999"), s)[0] == 403  # another local page too
    with_tokens = Settings(tokens={"alice": "alice-token-0001"})  # the token is the defence: nothing checked
    assert refusal(scope("attacker.example", "https://attacker.example"), with_tokens) is None


def test_allow_lists_are_settings_and_are_checked():
    s = load_settings(env={"SHADOWOPT_ALLOWED_HOSTS": "shadow.lan, [fd00::1]",
                           "SHADOWOPT_ALLOWED_ORIGINS": "http://tool.lan:3000"})
    assert s.allowed_hosts == ["shadow.lan", "[fd00::1]"] and s.allowed_origins == ["http://tool.lan:3000"]
    assert refusal(scope("shadow.lan:8000", "http://tool.lan:3000/"), s) is None
    assert refusal(scope("[fd00::1]:8000"), s) is None
    for env, shown in (({"SHADOWOPT_ALLOWED_HOSTS": "http://shadow.lan"}, "allowed_hosts"),
                       ({"SHADOWOPT_ALLOWED_ORIGINS": "tool.lan"}, "allowed_origins")):
        with pytest.raises(SettingsError, match=shown):
            load_settings(env=env)


def test_serving_beyond_loopback_without_tokens_needs_an_allow_list():
    assert "allowed_hosts" in check_host(Settings(host="0.0.0.0"))
    assert check_host(Settings(host="0.0.0.0", allowed_hosts=["shadow.lan"])) is None
    assert check_host(Settings(host="0.0.0.0", tokens={"alice": "alice-token-0001"})) is None
    assert check_host(Settings()) is None
