"""A Schemathesis check for tests/service/test_api_fuzz.py (loaded through SCHEMATHESIS_HOOKS): a schema-valid request
may be refused (422) only for a rule its schema cannot state, never for one it does.

Where an operation's body carries rules JSON Schema cannot express (a spec's checks across fields, an upload that
must decode as its name says, `frame` below the spec's frames), the fuzz test lets positive_data_acceptance take 422,
as the operation's 422 response declares. This check keeps that allowance narrow: each line of such a 422 must name
a rule, not one of the constraints the schema states (a type, a bound, a length, a required or unknown key), whose
messages come from pydantic or FastAPI. The one exception is an integer written as a whole float (`2.0`): JSON Schema
counts it as an integer, this API does not (docs/service.md), and no schema keyword can tell the two apart.
"""

from __future__ import annotations

import re
from typing import Any

import schemathesis

# pydantic's and FastAPI's messages for what a schema states; a rule's own message (a validator's) is anything else.
SCHEMA_STATED = re.compile(
    r"(Input should |Field required|Extra inputs are not permitted|(String|List|Tuple|Dictionary|Value) should have "
    r"|Expected UploadFile)"
)


def value_at(body: Any, where: str) -> Any:
    """The value a dotted error location (`targets.assets.0.variants`) names in a request body, or None."""
    node = body
    for part in where.split("."):
        if isinstance(node, dict):
            if part not in node and (node.get("kind") == part or part == "0"):
                # a tagged union's tag (`placement.water.school`: the placement whose kind is water), or a list's
                # first item given as the one mapping the list form stands for (`targets.0.count` of `targets: {}`)
                continue
            node = node.get(part)
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            return None
    return node


def stated_by_the_schema(line: str, body: Any) -> bool:
    """Whether one line of a 422's `errors` refuses a constraint the schema states (a whole float taken as an
    integer aside)."""
    where, _, why = line.partition(": ")
    if not SCHEMA_STATED.match(why):
        return False
    value = value_at(body, where)
    return not (isinstance(value, float) and value.is_integer())


@schemathesis.check
def refused_only_for_rules_the_schema_cannot_state(ctx, response, case) -> bool | None:
    if response.status_code != 422 or case.meta is None or not case.meta.generation.mode.is_positive:
        return None
    try:
        lines = response.json()["errors"]
    except (ValueError, KeyError, TypeError):
        raise AssertionError(f"422 without the error body: {response.text[:500]}") from None
    stated = [line for line in lines if stated_by_the_schema(line, case.body)]
    if stated:
        raise AssertionError("A schema-valid request was refused for a constraint its schema states (the schema and "
                             "the API disagree):\n" + "\n".join(stated))
    return None
