"""Types of JSON documents whose shape is open (specs as stored, summaries, records read back from files).

Documents with a fixed shape have their own TypedDict next to the code that builds them (job.json in
job_document.py); these aliases are for the rest. Read JSON as `Mapping[str, object]` and narrow what you use.
"""

from __future__ import annotations

from typing import TypeAlias

JSONValue: TypeAlias = "str | int | float | bool | None | list[JSONValue] | dict[str, JSONValue]"
JSONObject: TypeAlias = "dict[str, JSONValue]"
