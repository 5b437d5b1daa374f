"""Headless matplotlib drawing of env states (RGB frames for GIFs/MP4s, ``render()`` of the adapters).

``render_frame(env, state)`` draws one (unbatched) state: the arena, the waypoint box, each robot
as a disc with its heading and safety radius, and the scenario's own layers (goals, prey, zones,
tiles) from ``scenario.render_layers(state)``. Returns ``uint8 [H, W, 3]``. ``FrameDrawer`` does the
same for many states of one env, reusing one figure and its static background.
``record_episodes`` plays one episode in each of several vmapped envs (a policy or random
actions) and ``render_grid_episode`` tiles their frames into one movie; ``save_movie`` writes a GIF
(imageio) or an MP4 (imageio-ffmpeg, when installed).
"""
from __future__ import annotations

import warnings

import numpy as np

AGENT_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")


class FrameDrawer:
    """Draws states of one env onto one reused figure: RGB ``uint8 [H, W, 3]`` per call.

    The static parts (arena, waypoint box, axes) are drawn once and kept as a background; each call
    restores it and draws only that state's robots, scenario layers and title on top (matplotlib
    blitting), much less work per frame than building a fresh figure. One drawer per env, size and dpi.
    """

    def __init__(self, env, *, size=(6.4, 4.2), dpi: int = 80):
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.transforms import offset_copy

        self.env, self._plt = env, plt
        x_min, x_max, y_min, y_max = env.params.arena
        fig = plt.Figure(figsize=size, dpi=dpi)
        self._canvas = FigureCanvasAgg(fig)
        ax = self._ax = fig.add_axes([0.02, 0.02, 0.96, 0.9])
        ax.set_xlim(x_min - 0.05, x_max + 0.05)
        ax.set_ylim(y_min - 0.05, y_max + 0.05)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_autoscale_on(False)
        c = env.config
        # the arena's edge and the waypoint box are drawn with each frame (in z-order: over a scenario's
        # tiles), so they are hidden in the background
        self._outlines = [
            ax.add_patch(plt.Rectangle((x_min, y_min), x_max - x_min, y_max - y_min, fill=False, lw=2, color="black")),
            ax.add_patch(plt.Rectangle((c.x_min, c.y_min), c.x_max - c.x_min, c.y_max - c.y_min, fill=False, lw=0.6,
                                       ls="--", color="grey"))]
        # where ax.set_title would put the title (6 points above the axes), as a per-frame artist
        self._title_at = offset_copy(ax.transAxes, fig=fig, y=6, units="points")
        for outline in self._outlines:
            outline.set_visible(False)
        self._canvas.draw()
        self._background = self._canvas.copy_from_bbox(fig.bbox)
        for outline in self._outlines:
            outline.set_visible(True)
        self._radius = env.params.robot_diameter / 2
        self._safety = env.barrier.si_radius / 2 if env.barrier is not None else None

    def __call__(self, state, *, step: int | None = None, reward: float | None = None) -> np.ndarray:
        """The frame of one (unbatched) env state (numpy or JAX leaves)."""
        ax, plt, radius, safety = self._ax, self._plt, self._radius, self._safety
        artists = [_draw_layer(ax, plt, layer) for layer in self.env.scenario.render_layers(state.scenario)]
        for i, (x, y, theta) in enumerate(np.asarray(state.poses, dtype=float)):
            colour = AGENT_COLOURS[i % len(AGENT_COLOURS)]
            artists.append(ax.add_artist(plt.Circle((x, y), radius, color=colour, alpha=0.85)))
            artists += ax.plot([x, x + 1.3 * radius * np.cos(theta)], [y, y + 1.3 * radius * np.sin(theta)],
                               color="black", lw=1.5)
            if safety is not None:
                px, py = x + 0.05 * np.cos(theta), y + 0.05 * np.sin(theta)
                artists.append(ax.add_artist(plt.Circle((px, py), safety, fill=False, lw=0.5, ls=":", color=colour)))
            artists.append(ax.text(x, y, str(i), ha="center", va="center", fontsize=7, color="white"))
        title = self.env.name.replace("_", " ")
        if step is not None:
            title += f"   step {step}"
        if reward is not None:
            title += f"   return {reward:.2f}"
        artists.append(ax.text(0.5, 1.0, title, transform=self._title_at, ha="center", va="baseline", fontsize=9,
                               clip_on=False))
        self._canvas.restore_region(self._background)
        for artist in sorted(self._outlines + artists, key=lambda a: a.get_zorder()):   # stable: ties keep order
            ax.draw_artist(artist)
        image = np.asarray(self._canvas.buffer_rgba())[..., :3].copy()
        for artist in artists:
            artist.remove()
        return image


def render_frame(env, state, *, step: int | None = None, reward: float | None = None,
                 size=(6.4, 4.2), dpi: int = 80) -> np.ndarray:
    """RGB image ``[H, W, 3]`` of one env state (numpy or JAX leaves); for many frames reuse a
    :class:`FrameDrawer`."""
    return FrameDrawer(env, size=size, dpi=dpi)(state, step=step, reward=reward)


def episode_frames(env, policy, key, num_envs: int = 1, progress: bool = False) -> list[np.ndarray]:
    """Frames of one episode per env (tiled when ``num_envs > 1``); see :func:`record_episodes`."""
    return render_grid_episode(env, record_episodes(env, policy, key, num_envs)[0], progress=progress)


def record_episodes(env, policy, key, num_envs: int = 1):
    """One episode in each of ``num_envs`` vmapped envs, for rendering.

    ``policy``: ``None`` (uniform random), ``(key, obs [K, N, D]) -> actions [K, N]`` or a
    :class:`marbler_jax.rollout.StatefulPolicy`. Envs that finish keep their final state.

    Returns ``(states, returns [T + 1, K], lengths [K])``: ``states`` is the env state pytree
    stacked as ``[T + 1, K, ...]`` (entry 0 the reset state), ``T = env.max_steps``, and
    ``lengths`` the steps each episode took.
    """
    import jax
    import jax.numpy as jnp

    from marbler_jax.rollout import StatefulPolicy, random_actions

    stateful = isinstance(policy, StatefulPolicy)

    def run(key):
        key_reset, key_run = jax.random.split(key)
        obs, state = jax.vmap(env.reset)(jax.random.split(key_reset, num_envs))
        memory = policy.initial_carry((num_envs,)) if stateful else ()

        def body(carry, key_t):
            obs, state, memory, done, first = carry
            key_act, key_step = jax.random.split(key_t)
            if policy is None:
                actions = random_actions(env, key_act, (num_envs,))
            elif stateful:
                actions, memory = policy.step(key_act, obs, memory, jnp.full((num_envs,), first))
            else:
                actions = policy(key_act, obs)
            new_obs, new_state, _, new_done, _ = jax.vmap(env.step_env)(
                jax.random.split(key_step, num_envs), state, actions)
            keep = lambda old, new: jnp.where(done.reshape(done.shape + (1,) * (new.ndim - 1)), old, new)
            state = jax.tree_util.tree_map(keep, state, new_state)
            obs = keep(obs, new_obs)
            return (obs, state, memory, done | new_done, False), state

        start = (obs, state, memory, jnp.zeros((num_envs,), bool), True)
        _, states = jax.lax.scan(body, start, jax.random.split(key_run, env.max_steps))
        return jax.tree_util.tree_map(lambda first, rest: jnp.concatenate([first[None], rest]), state, states)

    states = jax.device_get(jax.jit(run)(key))
    returns = np.asarray(states.episode_return)
    steps = np.asarray(states.step)
    return states, returns, steps.max(axis=0)


def render_grid_episode(env, states, *, columns: int | None = None, dpi: int | None = None,
                        progress: bool = False) -> list[np.ndarray]:
    """Frames ``[H, W, 3]`` tiling the envs of :func:`record_episodes` states (``[T + 1, K, ...]``) in
    a grid, one frame per step until the longest episode ended (finished envs hold their last frame)."""
    import jax

    steps = np.asarray(states.step)                                   # [T + 1, K]
    count = steps.shape[1]
    length = int(steps.max())
    dpi = dpi or (80 if count == 1 else 60)
    columns = columns or int(np.ceil(np.sqrt(count)))
    rows = int(np.ceil(count / columns))
    frames = []
    times = range(length + 1)
    if progress:
        from tqdm.auto import tqdm

        times = tqdm(times, desc="render", unit="frame")
    draw = FrameDrawer(env, dpi=dpi)
    for t in times:
        tiles = []
        for k in range(count):
            one = jax.tree_util.tree_map(lambda x: x[t, k], states)
            tiles.append(draw(one, step=int(steps[t, k]), reward=float(one.episode_return)))
        blank = np.full_like(tiles[0], 255)
        tiles += [blank] * (rows * columns - count)
        grid = [np.concatenate(tiles[r * columns:(r + 1) * columns], axis=1) for r in range(rows)]
        frames.append(np.concatenate(grid, axis=0))
    return frames


def save_movie(frames, path, fps: float = 6.0) -> None:
    """Write ``frames`` to ``path``: ``.gif`` (imageio) or ``.mp4`` (needs ``imageio-ffmpeg``)."""
    from pathlib import Path

    import imageio.v2 as imageio

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"movie file must end in .gif or .mp4, got {path.name!r}")
    if not (isinstance(fps, (int, float)) and not isinstance(fps, bool) and 0 < fps <= 100):
        raise ValueError(f"fps must be a number in (0, 100] frames per second, got {fps!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".gif":
        # imageio's pillow writer takes the frame duration in milliseconds (GIF stores hundredths of a second)
        imageio.mimsave(path, np.stack(frames), duration=1000.0 / fps, loop=0)
        return
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise ValueError("writing .mp4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg); "
                         "or write a .gif") from None
    even = [f[: f.shape[0] // 2 * 2, : f.shape[1] // 2 * 2] for f in frames]   # H.264 wants even sizes
    with warnings.catch_warnings():
        # imageio-ffmpeg starts ffmpeg by fork + exec: the child runs no JAX code, so JAX's fork warning is moot
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        imageio.mimsave(path, even, fps=fps, macro_block_size=1)


def _draw_layer(ax, plt, layer: dict):
    """Adds one ``render_layers`` entry to ``ax``; returns its artist."""
    kind = layer["kind"]
    if kind == "points":
        pts = np.asarray(layer["xy"], dtype=float).reshape(-1, 2)
        return ax.scatter(pts[:, 0], pts[:, 1], s=layer.get("size", 40), marker=layer.get("marker", "o"),
                          c=layer.get("color", "black"), alpha=layer.get("alpha", 1.0), zorder=3)
    if kind == "rect":
        x0, y0, w, h = layer["xywh"]
        return ax.add_artist(plt.Rectangle((x0, y0), w, h, color=layer.get("color", "grey"),
                                           alpha=layer.get("alpha", 0.25), lw=0))
    if kind == "circle":
        (x, y), r = layer["xy"], layer["r"]
        return ax.add_artist(plt.Circle((x, y), r, color=layer.get("color", "grey"), alpha=layer.get("alpha", 0.25),
                                        lw=0))
    if kind == "text":
        x, y = layer["xy"]
        return ax.text(x, y, layer["text"], fontsize=layer.get("size", 8), ha="center", va="center")
    if kind == "image":
        return ax.imshow(layer["rgb"], extent=layer["extent"], alpha=layer.get("alpha", 0.5), zorder=0,
                         interpolation="nearest")
    raise ValueError(f"unknown render layer kind {kind!r}")
