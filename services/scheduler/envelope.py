"""`render.cue` messages built once per queue and pushed straight into Redis (the scheduler's hot send path).

Celery + kombu spend ~50 us of CPU per message (header dicts, option merging, serialising, base64, retry
wrappers) to publish what is, for the scheduler, always the same message with three values changed: the task
id argument, the Celery task id (also the correlation and root id) and kombu's delivery tag. An `Envelope`
asks Celery for that message once (`amqp.create_task_message`: the exact protocol-2 headers), lays it out the
way kombu's Redis transport stores a message (a JSON envelope with a base64 body, `Channel._put`'s LPUSH onto
the queue's list) with placeholders, and then fills the placeholders in per task: one LPUSH per queue and
batch.

The layout is kombu's, not a public API: tests/scheduler/test_transport.py compares an Envelope's message with
one kombu itself published, so an upgrade that changes the layout fails there rather than in production.
"""

from __future__ import annotations

import base64
import json
import os
import re
from collections.abc import Sequence

from celery import Celery
from redis import Redis

from services.core.celery_config import TASK_RENDER_CUE
from services.core.domain.json_types import JSONObject

_ID = "\x00celery-id\x00"  # placeholders; they cannot occur in Celery's headers
_TAG = "\x00delivery-tag\x00"
_BODY = "\x00body\x00"
_ARGS = "\x00argsrepr\x00"
# protocol 2's body: (args, kwargs, embed) as kombu's JSON serializer writes it, then base64 (kombu's Redis
# channel)
_BODY_JSON = '[[{}], {{}}, {{"callbacks": null, "errbacks": null, "chain": null, "chord": null}}]'


def _uuid4_text(h: str) -> str:
    """A version-4 UUID's text from 32 random hex digits (what str(uuid.uuid4()) gives, for a third of the
    CPU)."""
    variant = "89ab"[int(h[16], 16) & 3]
    return f"{h[:8]}-{h[8:12]}-4{h[13:16]}-{variant}{h[17:20]}-{h[20:32]}"


def _two_uuid4s() -> tuple[str, str]:
    h = os.urandom(32).hex()
    return _uuid4_text(h[:32]), _uuid4_text(h[32:])


class Envelope:
    """The serialized `render.cue` message for one queue, with the per-task values left open."""

    def __init__(self, app: Celery, queue: str, origin: str) -> None:
        message = app.amqp.create_task_message(
            _ID, TASK_RENDER_CUE, [0], {}, root_id=_ID, origin=origin,
            argsrepr=_ARGS, kwargsrepr="{}", ignore_result=True,
        )
        headers = {k: v for k, v in message.headers.items()}
        envelope: JSONObject = {
            "body": _BODY,
            "content-encoding": "utf-8",
            "content-type": "application/json",
            "headers": headers,
            "properties": {
                "correlation_id": _ID,
                "reply_to": "",
                "delivery_mode": 2,  # persistent, as Celery's default
                "delivery_info": {"exchange": "", "routing_key": queue},
                "priority": 0,
                "body_encoding": "base64",
                "delivery_tag": _TAG,
            },
        }
        # the JSON text split at the placeholders (json.dumps writes \x00 as \u0000): parts and slots
        # alternate
        marks = {json.dumps(m)[1:-1]: m for m in (_ID, _TAG, _BODY, _ARGS)}
        pieces = re.split("(" + "|".join(re.escape(k) for k in marks) + ")", json.dumps(envelope))
        self._parts = pieces[0::2]
        self._slots = [marks[k] for k in pieces[1::2]]
        self.queue = queue

    def message(self, task_id: int) -> str:
        """The JSON text kombu would LPUSH for `render.cue(task_id)` (fresh task id and delivery tag)."""
        tid = int(task_id)
        task_uuid, tag = _two_uuid4s()
        values = {
            _ID: task_uuid,
            _TAG: tag,
            _BODY: base64.b64encode(_BODY_JSON.format(tid).encode()).decode("ascii"),
            _ARGS: f"[{tid}]",
        }
        out = [self._parts[0]]
        for slot, part in zip(self._slots, self._parts[1:], strict=True):
            out.append(values[slot])
            out.append(part)
        return "".join(out)

    def push(self, client: Redis, task_ids: Sequence[int]) -> None:
        """LPUSH one message per task onto the queue's list in one command (kept in order: workers pop the
        oldest first)."""
        if task_ids:
            client.lpush(self.queue, *[self.message(t) for t in task_ids])
