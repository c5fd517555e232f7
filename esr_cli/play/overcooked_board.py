"""Overcooked as `esr play` shows it: a board with every object drawn so that a person can tell
them apart at a glance (JaxMARL's debug renderer draws onions, plates, soups and pots as small
look-alike shapes).

The picture is read from the JaxMARL state (esr_cli/model/envs/overcooked.py wraps it):
`maze_map[y, x] = (object, colour, status)` inside a padding of walls, with agents, loose items
on counters and pots (their status: 23 empty, 22-20 one to three onions, 19-1 cooking steps
left, 0 ready) in it, and each agent's cell, facing and held item in `agent_pos`,
`agent_dir_idx` and `agent_inv`.

Every cell is one of a few dozen tiles (a floor, a counter with or without an item, a pot in
one of its 24 states, an agent facing one of 4 ways holding one of 4 things, ...). Each tile is
drawn once, the first time it is needed (supersampled, so its edges are smooth), and a frame is
the tiles put side by side: well under a millisecond on a small layout.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont

CELL_PX = 48  # a cell's side in the picture
SUPERSAMPLE = 4  # tiles are drawn this many times larger, then reduced (smooth edges)

# JaxMARL's OBJECT_TO_INDEX (jaxmarl/environments/overcooked/common.py) and pot statuses
# (overcooked.py), copied so that drawing needs no jaxmarl import.
EMPTY, WALL, ONION, ONION_PILE, PLATE, PLATE_PILE, GOAL, POT, DISH, AGENT = 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
POT_EMPTY, POT_FULL, POT_READY = 23, 20, 0  # 20: three onions, cooking starts; counts down to 0
COOK_STEPS = POT_FULL - POT_READY
# JaxMARL's facing indices (DIR_TO_VEC): north, south, east, west, as (dx, dy) on the picture.
FACING = {0: (0, -1), 1: (0, 1), 2: (1, 0), 3: (-1, 0)}
HELD = {EMPTY: None, ONION: "onion", PLATE: "plate", DISH: "soup"}  # agent_inv -> what a hand holds
ON_COUNTER = {ONION: "onion", PLATE: "plate", DISH: "soup"}  # loose items, always on a plain counter

# Colours, named in LEGEND. The person and the robot are blue and red, as in JaxMARL's renderer
# when the robot plays agent_0, but here whatever seat the person plays.
YOU = (40, 110, 235)
ROBOT = (220, 45, 55)
FLOOR = (232, 224, 208)
FLOOR_LINE = (212, 202, 182)
COUNTER = (170, 120, 74)
COUNTER_EDGE = (118, 80, 46)
CRATE = (98, 64, 36)
ONION_FILL, ONION_LINE, SPROUT = (245, 196, 40), (150, 100, 10), (90, 160, 50)
PLATE_FILL, PLATE_LINE = (252, 252, 252), (150, 150, 150)
SOUP = (215, 105, 25)
POT_BODY, POT_INSIDE = (52, 54, 60), (92, 96, 104)
BAR_TRACK, COOKING_BAR, READY = (40, 40, 40), (245, 150, 30), (60, 200, 80)
SERVE_FILL, SERVE_LINE = (72, 160, 90), (230, 245, 230)
OUTLINE = (30, 30, 30)

LEGEND = ("blue: you · red: the robot (the arrow shows which way each faces; what each holds is drawn in front "
          "of it) · yellow ball: onion · white disc: plate · orange on a plate: soup · dark round pot: its yellow "
          "dots are the onions in it (3 start it cooking), its orange bar fills while it cooks, a green bar and a "
          "tick: the soup is ready · crate of onions: onion pile · stack of plates: plate pile · green SERVE square: "
          "serving window · brown: counter (things can be put down there)")


class Pen:
    """ImageDraw on one supersampled tile, in cell units: (0, 0) the top left, (1, 1) the bottom right."""

    def __init__(self, image: Image.Image):
        self.draw, self.side = ImageDraw.Draw(image), image.width

    def _px(self, v: float) -> float:
        return v * self.side

    def box(self, x0, y0, x1, y1, fill, outline=None, width=0.0, radius=0.0):
        self.draw.rounded_rectangle([self._px(x0), self._px(y0), self._px(x1) - 1, self._px(y1) - 1], self._px(radius),
                                    fill=fill, outline=outline, width=round(self._px(width)))

    def disc(self, cx, cy, r, fill, outline=None, width=0.0):
        self.draw.ellipse([self._px(cx - r), self._px(cy - r), self._px(cx + r), self._px(cy + r)], fill=fill,
                          outline=outline, width=round(self._px(width)))

    def ellipse(self, cx, cy, rx, ry, fill, outline=None, width=0.0):
        self.draw.ellipse([self._px(cx - rx), self._px(cy - ry), self._px(cx + rx), self._px(cy + ry)], fill=fill,
                          outline=outline, width=round(self._px(width)))

    def polygon(self, points, fill, outline=None, width=0.0):
        self.draw.polygon([(self._px(x), self._px(y)) for x, y in points], fill=fill, outline=outline,
                          width=round(self._px(width)))

    def line(self, points, fill, width):
        self.draw.line([(self._px(x), self._px(y)) for x, y in points], fill=fill, width=round(self._px(width)),
                       joint="curve")

    def text(self, cx, cy, words: str, size: float, fill):
        font = ImageFont.load_default(size=self._px(size))
        self.draw.text((self._px(cx), self._px(cy)), words, fill=fill, font=font, anchor="mm")


# ---------------------------------------------------------------- the pieces of a tile
def floor(pen: Pen) -> None:
    pen.box(0, 0, 1, 1, FLOOR, outline=FLOOR_LINE, width=0.03)


def counter(pen: Pen) -> None:
    pen.box(0, 0, 1, 1, COUNTER_EDGE)
    pen.box(0.05, 0.05, 0.95, 0.95, COUNTER, radius=0.06)


def onion(pen: Pen, cx: float, cy: float, r: float) -> None:
    pen.line([(cx, cy - r * 0.8), (cx + r * 0.35, cy - r * 1.45)], SPROUT, r * 0.35)
    pen.disc(cx, cy, r, ONION_FILL, ONION_LINE, r * 0.16)


def plate(pen: Pen, cx: float, cy: float, r: float) -> None:
    pen.disc(cx, cy, r, PLATE_FILL, PLATE_LINE, r * 0.12)
    pen.disc(cx, cy, r * 0.62, None, PLATE_LINE, r * 0.06)


def soup(pen: Pen, cx: float, cy: float, r: float) -> None:
    pen.disc(cx, cy, r, PLATE_FILL, PLATE_LINE, r * 0.12)
    pen.disc(cx, cy, r * 0.68, SOUP)


ITEM = {"onion": onion, "plate": plate, "soup": soup}


def tick(pen: Pen, cx: float, cy: float, size: float, fill) -> None:
    pen.line([(cx - size, cy), (cx - size * 0.3, cy + size * 0.7), (cx + size, cy - size * 0.8)], fill, size * 0.45)


# ---------------------------------------------------------------- the tiles
def draw_counter(pen: Pen, item: str | None) -> None:
    counter(pen)
    if item is not None:
        ITEM[item](pen, 0.5, 0.52, 0.27)


def draw_onion_pile(pen: Pen) -> None:
    counter(pen)
    pen.box(0.12, 0.3, 0.88, 0.9, CRATE, outline=OUTLINE, width=0.03, radius=0.05)
    for cx, cy in ((0.32, 0.45), (0.68, 0.45), (0.5, 0.3)):
        onion(pen, cx, cy, 0.15)
    pen.box(0.12, 0.55, 0.88, 0.9, CRATE, outline=OUTLINE, width=0.03, radius=0.05)  # the crate's front


def draw_plate_pile(pen: Pen) -> None:
    counter(pen)
    for dy in (0.2, 0.1, 0.0):
        pen.ellipse(0.5, 0.42 + dy, 0.36, 0.2, PLATE_FILL, PLATE_LINE, 0.035)


def draw_serving_window(pen: Pen) -> None:
    counter(pen)
    pen.box(0.1, 0.1, 0.9, 0.9, SERVE_FILL, outline=SERVE_LINE, width=0.04, radius=0.08)
    pen.text(0.5, 0.5, "SERVE", 0.22, SERVE_LINE)


def draw_pot(pen: Pen, status: int) -> None:
    """A pot seen from above: yellow dots for the onions in it; once cooking, soup inside and a
    bar under it that fills up; when ready, a full green bar and a tick."""
    counter(pen)
    pen.box(0.04, 0.4, 0.96, 0.52, POT_BODY, radius=0.05)  # handles
    pen.disc(0.5, 0.44, 0.36, POT_BODY, OUTLINE, 0.02)
    cooking_or_ready = status <= POT_FULL
    pen.disc(0.5, 0.44, 0.27, SOUP if cooking_or_ready else POT_INSIDE)
    if not cooking_or_ready:
        for cx, cy in ((0.37, 0.52), (0.63, 0.52), (0.5, 0.33))[: POT_EMPTY - status]:
            onion(pen, cx, cy, 0.11)
        return
    done = (POT_FULL - status) / COOK_STEPS
    pen.box(0.1, 0.84, 0.9, 0.96, BAR_TRACK, radius=0.03)
    pen.box(0.1, 0.84, 0.1 + 0.8 * max(done, 0.06), 0.96, READY if status == POT_READY else COOKING_BAR, radius=0.03)
    if status == POT_READY:
        pen.disc(0.5, 0.44, 0.2, READY, OUTLINE, 0.02)
        tick(pen, 0.5, 0.45, 0.12, (255, 255, 255))


def draw_agent(pen: Pen, colour, facing: int, held: str | None) -> None:
    """A disc in the agent's colour with an arrow out of its front (to the cell's edge, so that
    the way it faces shows even at a glance); what it holds sits on its front edge."""
    floor(pen)
    dx, dy = FACING[facing]
    tip, base = (0.5 + 0.48 * dx, 0.5 + 0.48 * dy), (0.5 + 0.32 * dx, 0.5 + 0.32 * dy)
    side = (0.2 * -dy, 0.2 * dx)  # half the arrow's base, across the facing
    corners = [tip, (base[0] + side[0], base[1] + side[1]), (base[0] - side[0], base[1] - side[1])]
    pen.polygon(corners, colour, OUTLINE, 0.02)
    pen.disc(0.5, 0.5, 0.3, colour, OUTLINE, 0.03)
    if held is not None:
        ITEM[held](pen, 0.5 + 0.14 * dx, 0.5 + 0.14 * dy, 0.16)


@cache
def tile(kind: str, detail=None, cell_px: int = CELL_PX) -> np.ndarray:
    """One cell's picture, uint8[cell_px, cell_px, 3], drawn on first use. kind/detail: "floor";
    "counter", item or None; "onion_pile"; "plate_pile"; "serve"; "pot", status;
    "you"/"robot", (facing, held)."""
    image = Image.new("RGB", (cell_px * SUPERSAMPLE, cell_px * SUPERSAMPLE), FLOOR)
    pen = Pen(image)
    if kind == "floor":
        floor(pen)
    elif kind == "counter":
        draw_counter(pen, detail)
    elif kind == "onion_pile":
        draw_onion_pile(pen)
    elif kind == "plate_pile":
        draw_plate_pile(pen)
    elif kind == "serve":
        draw_serving_window(pen)
    elif kind == "pot":
        draw_pot(pen, detail)
    elif kind in ("you", "robot"):
        draw_agent(pen, YOU if kind == "you" else ROBOT, *detail)
    else:
        raise ValueError(f"no tile {kind!r}")
    array = np.asarray(image.reduce(SUPERSAMPLE), dtype=np.uint8)
    array.flags.writeable = False  # shared by every frame
    return array


def cell_tile(obj: int, status: int, cell_px: int) -> np.ndarray:
    """The tile of a cell of the maze map without an agent."""
    if obj == POT:
        return tile("pot", int(min(status, POT_EMPTY)), cell_px)
    if obj == ONION_PILE:
        return tile("onion_pile", None, cell_px)
    if obj == PLATE_PILE:
        return tile("plate_pile", None, cell_px)
    if obj == GOAL:
        return tile("serve", None, cell_px)
    if obj in ON_COUNTER:
        return tile("counter", ON_COUNTER[obj], cell_px)
    if obj == WALL:
        return tile("counter", None, cell_px)
    return tile("floor", None, cell_px)  # empty floor, and an agent's cell under the agent


def draw(state, height: int, width: int, person: int, cell_px: int = CELL_PX) -> np.ndarray:
    """uint8[height*cell_px, width*cell_px, 3]: the board of a JaxMARL Overcooked state; `person`
    is the JaxMARL agent index the person plays (drawn as "you"; the other agent is the robot)."""
    maze = np.asarray(state.maze_map)
    pad = (maze.shape[0] - height) // 2
    inner = maze[pad:pad + height, pad:pad + width]
    tiles = [[cell_tile(int(obj), int(status), cell_px) for obj, _, status in row] for row in inner]
    for agent, ((x, y), facing, held) in enumerate(zip(np.asarray(state.agent_pos), np.asarray(state.agent_dir_idx),
                                                        np.asarray(state.agent_inv))):
        tiles[int(y)][int(x)] = tile("you" if agent == person else "robot", (int(facing), HELD.get(int(held))), cell_px)
    return np.concatenate([np.concatenate(row, axis=1) for row in tiles], axis=0)


def draw_env(env, state, cell_px: int = CELL_PX) -> np.ndarray:
    """The board of esr's Overcooked `env` in `state`, the human's seat drawn as "you"."""
    return draw(state, env.height, env.width, 1 - env.robot_seat, cell_px)
