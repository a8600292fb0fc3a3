"""The evidence that chose an up, in words: `omnidata plan`'s "chosen for ..." and job.json's `reason`."""

from __future__ import annotations

from services.core.ingest.frame.up_evidence import SIGN_FREE_TERMS, UpDecision

# why up is what it is, when no scoring of candidates decided it (`UpEstimate.record`'s "reason")
METHOD_WORDS = {
    "floor": "the floor",
    "convention": "the file format's convention (no floor or support base found)",
    "convention-tie": "the file format's convention (floor and ceiling look alike)",
    "base": "an object's support base",
    "given": "the up given",
    "source_to_world": "the source_to_world given",
    "recorded_gravity": "the gravity recorded with the scan (no floor found to weigh against it)",
}

# the evidence terms of `up_evidence`
TERM_WORDS = {
    "levelled_axis": "a floor on a source axis (the file was levelled)",
    "format_up": "the format's up axis (its convention)",
    "camera_frame": "an upright camera's frame (the scan lies ahead of its origin)",
    "camera_height": "the camera's height (no floor lies further below it than a storey)",
    "camera_looked_down": "the camera looked down at it from a hand's height",
    "capture_up": "the capture's cameras",
    "recorded_gravity": "the gravity recorded with the scan",
    "floor_area": "the floor's area",
    "furniture": "furniture tops seen from above (support surfaces)",
    "extent": "a room wider than tall",
    "storey": "a storey's height",
    "view_direction": "a single view's direction",
    "view_aspect": "a single view's landscape frame",
}


def reason_words(decision: UpDecision) -> str:
    """Which evidence set the chosen up apart from the runner-up, in words (the one or two largest terms)."""
    best, runner = decision.best, decision.runner_up
    if runner is None:
        return "no other candidate levels the scan differently"
    gain = {k: best.terms.get(k, 0.0) - runner.terms.get(k, 0.0) for k in {*best.terms, *runner.terms}}
    if "mirror" in gain:  # one plane's two signs: the geometry's lead is the cap, named by its largest term
        geometry = {k: gain.pop(k) for k in SIGN_FREE_TERMS if k in gain}
        capped = sum(geometry.values()) + gain.pop("mirror")
        if geometry:
            gain[max(geometry, key=lambda k: geometry[k])] = capped
    ranked = sorted(((v, k) for k, v in gain.items()), reverse=True)
    named = [TERM_WORDS.get(k, k) for v, k in ranked[:2] if v > 0.25]
    return ", ".join(named) if named else "the sum of weak evidence"
