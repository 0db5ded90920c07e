"""Records is the one door to Redis, read off the source with ast: outside seasynth.service.records no module reaches
a Records object's client, prefix, keys or scripts, registers a Lua script, or uses redis-py for more than naming its
exceptions (two bench modules aside, which start a Redis server of their own and wait for it to answer)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("service", "worker", "api", "cli", "bench")
DOOR = ROOT / "service" / "records"
# Modules that make a redis-py client of their own, and why: not to reach the records.
CLIENT_MAKERS = {
    "bench/enqueue.py": "starts redis-server for the benchmark and pings it until it answers",
    "bench/stack.py": "starts redis-server for the benchmark stack and pings it until it answers",
}


def outside_the_door() -> dict[str, ast.Module]:
    return {str(p.relative_to(ROOT)): ast.parse(p.read_text(), filename=str(p))
            for folder in FOLDERS for p in sorted((ROOT / folder).rglob("*.py")) if DOOR not in p.parents}


MODULES = outside_the_door()


def names_records(node: ast.expr) -> bool:
    """Whether an expression is, by the project's naming, a Records object: `records`, `ctx.records`,
    `services.records`, `self._records`..."""
    name = node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else ""
    return name.lstrip("_") == "records"


def records_members() -> set[str]:
    from seasynth.service.records.store import Records

    return {name for name in dir(Records) if not name.startswith("_")}


def test_records_members_reached_from_outside_are_public_methods():
    public = records_members()
    reached, offenders = 0, []
    for path, tree in MODULES.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and names_records(node.value):
                reached += 1
                if node.attr not in public:
                    offenders.append(f"{path}:{node.lineno} .{node.attr}")
    assert offenders == []
    assert reached > 50, "the check found too few uses of Records to hold anything"


def test_records_keep_client_prefix_and_keys_private():
    import redis

    from seasynth.service.records.store import Records

    records = Records(redis.Redis(), "door")  # registering scripts computes their sha locally: no connection
    assert not {"r", "p", "_k"} & set(dir(records))
    assert {"_r", "_prefix", "_key"} <= set(dir(records))


def test_lua_scripts_are_registered_only_behind_the_door():
    offenders = []
    for path, tree in MODULES.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr in ("register_script", "script_load", "evalsha"):
                offenders.append(f"{path}:{node.lineno} .{node.attr}")
            elif isinstance(node, ast.Constant) and isinstance(node.value, str) and "redis.call(" in node.value:
                offenders.append(f"{path}:{node.lineno} Lua")
    assert offenders == []


def test_redis_py_is_used_outside_the_door_only_to_name_its_errors():
    """`import redis` outside seasynth.service.records: for `except redis.RedisError` and the like, never a client;
    Records.from_url and raw_client (seasynth.service.records.store) make the project's clients."""
    offenders = []
    for path, tree in MODULES.items():
        if path in CLIENT_MAKERS:
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "redis":
                offenders += [f"{path}:{node.lineno} from {node.module} import {a.name}" for a in node.names
                              if not a.name.endswith("Error")]
            elif (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "redis"
                  and not node.attr.endswith("Error") and node.attr != "exceptions"):
                offenders.append(f"{path}:{node.lineno} redis.{node.attr}")
    assert offenders == []


def test_records_are_built_from_a_url_outside_the_door():
    """Records(client, prefix) takes a client: outside the door, Records.from_url(url, prefix) builds them."""
    offenders = [f"{path}:{node.lineno}" for path, tree in MODULES.items() for node in ast.walk(tree)
                 if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "Records"]
    assert offenders == []


def test_the_exceptions_are_still_client_makers():
    """An exception that no longer makes a client is dropped from CLIENT_MAKERS, so the list stays exact."""
    for path in CLIENT_MAKERS:
        calls = [node for node in ast.walk(MODULES[path]) if isinstance(node, ast.Attribute)
                 and isinstance(node.value, ast.Name) and node.value.id == "redis" and node.attr == "Redis"]
        assert calls, f"{path} makes no redis-py client any more: remove it from CLIENT_MAKERS"
