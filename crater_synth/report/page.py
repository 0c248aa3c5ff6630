"""The page: a Jinja2 environment over ``templates/`` (package data), the filters the templates use,
and :func:`render_page`, which gathers every section and renders it with its template."""

from __future__ import annotations

import datetime as _dt
import functools
import math
from importlib import resources

import jinja2
from markupsafe import Markup

from crater_synth import __version__
from crater_synth.report import gather
from train.registry import label

_NARROW_NBSP = "&#8239;"


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def pct(x, digits: int = 1):
    """Accuracy as a percentage ("–" when missing or NaN)."""
    return Markup(f"{100.0 * float(x):.{digits}f}{_NARROW_NBSP}%") if _finite(x) else "–"


def hue(x) -> str:
    """Red (0) to green (120) background hue of an accuracy cell."""
    return f"{120.0 * max(0.0, min(1.0, float(x))):.0f}"


def duration(s) -> str:
    if not _finite(s):
        return "–"
    s = float(s)
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.2f} h"


def distance_km(x) -> str:
    """A position error: km from 0.1 km up, metres (3 significant digits) below ("–" when missing)."""
    if not _finite(x):
        return "–"
    x = float(x)
    return f"{x:.2f} km" if x >= 0.1 else f"{1000.0 * x:.3g} m"


def thousands(v) -> str:
    return f"{int(v):,}" if _finite(v) else "–"


@functools.lru_cache(maxsize=1)
def environment():
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("crater_synth.report", "templates"),
        autoescape=True,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )
    env.filters.update(
        pct=pct,
        hue=hue,
        duration=duration,
        thousands=thousands,
        distance_km=distance_km,
        model_label=label,
        fmt=lambda v, spec: spec.format(v),
    )
    env.tests["finite"] = _finite
    return env


def render_page(ctx: gather.Ctx) -> str:
    """Gather every section (drawing its figures into ``ctx.out``) and render the whole page."""
    env = environment()
    sections = []
    for sid, title, fn, intro in gather.SECTIONS:
        ctx.say(f"section {title}")
        html = env.get_template(f"{sid}.html.j2").render(d=fn(ctx))
        sections.append({"id": sid, "title": title, "intro": intro, "html": Markup(html)})
    css = resources.files("crater_synth.report").joinpath("templates/report.css").read_text(encoding="utf-8")
    generated = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return env.get_template("page.html.j2").render(
        h=gather.header(ctx), sections=sections, css=Markup(css), generated=generated, version=__version__
    )
