"""The one colour table of the project's pictures: the report's PNG figures and the viewer.

Each entry names a thing, not a hue; matplotlib takes the hex strings and the viewer embeds
the table (``DATA.colors``, CSS ``--c-<name>``), so a change here changes both.
"""

from __future__ import annotations

#: ``{thing: "#rrggbb"}``: every colour a figure or the viewer gives a thing.
COLORS: dict[str, str] = {
    # outcomes: the same two colours for every good and bad event, in every picture
    "good": "#1e8449",  # a crying baby pacified, the milk reached, a grandma rescued
    "bad": "#c0392b",  # a sleeping baby woken, a collision, an action that differs from base
    # FindMilk
    "crying": "#e69f00",  # a crying baby not reached yet (Okabe-Ito orange)
    "sleeping": "#56b4e9",  # a sleeping baby not reached yet (Okabe-Ito sky blue)
    "milk": "#f0c419",  # the milk (a gold star)
    "path": "#7e3ba8",  # the agent's path (the report draws it in the variant's colour)
    "agent": "#26282b",  # the robot, the agent's car, the end of a path
    "start": "#ffffff",  # the start of a path (a white triangle, dark edge)
    # Driving
    "road": "#6e6e6e",
    "lane_mark": "#f0f0f0",
    "car": "#d55e00",  # another car (Okabe-Ito vermillion)
    "grandma": "#009e73",  # a grandma to rescue (Okabe-Ito bluish green)
    # beliefs and policies (the viewer's bars; the report's diagnostics)
    "belief": "#0072b2",  # an agent's belief (Okabe-Ito blue)
    "fused": "#7a3bd8",  # the panel's fused belief
    "policy": "#ef6c00",  # the fine-tuned policy
    "base": "#9aa4ad",  # the base policy; the report's base line is "reference"
    "abstained": "#b0b7be",  # an agent that did not answer
    "conflict": "#8aa4e0",  # Dempster's conflict K
    "current": "#ffe0b2",  # the step shown
    "reference": "#262626",  # the base policy's value in an ablation figure (dashed)
    # page and figure ink
    "ink": "#1d2327",
    "muted": "#5f6b73",
    "grid": "#d5dbe0",
}


def css_variables(colors: dict[str, str] | None = None) -> str:
    """The table as one CSS rule of custom properties: ``:root { --c-good: #1e8449; ... }``."""
    table = COLORS if colors is None else colors
    body = " ".join(f"--c-{name.replace('_', '-')}: {value};" for name, value in table.items())
    return f":root {{ {body} }}\n"
