"""Headless matplotlib drawing of env states (RGB frames for GIFs, ``render()`` of the adapters).

``render_frame(env, state)`` draws one (unbatched) state: the arena, the waypoint box, each robot
as a disc with its heading and safety radius, and the scenario's own layers (goals, prey, zones,
tiles) from ``scenario.render_layers(state)``. Returns ``uint8 [H, W, 3]``.
"""
from __future__ import annotations

import numpy as np

AGENT_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")


def render_frame(env, state, *, step: int | None = None, reward: float | None = None,
                 size=(6.4, 4.2), dpi: int = 80) -> np.ndarray:
    """RGB image ``[H, W, 3]`` of one env state (numpy or JAX leaves)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    poses = np.asarray(state.poses, dtype=float)
    x_min, x_max, y_min, y_max = env.params.arena
    fig = plt.Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0.02, 0.02, 0.96, 0.9])
    ax.set_xlim(x_min - 0.05, x_max + 0.05)
    ax.set_ylim(y_min - 0.05, y_max + 0.05)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.add_patch(plt.Rectangle((x_min, y_min), x_max - x_min, y_max - y_min, fill=False, lw=2, color="black"))
    c = env.config
    ax.add_patch(plt.Rectangle((c.LEFT, c.UP), c.RIGHT - c.LEFT, c.DOWN - c.UP, fill=False, lw=0.6,
                               ls="--", color="grey"))
    for layer in env.scenario.render_layers(state.scenario):
        _draw_layer(ax, plt, layer)
    radius = env.params.robot_diameter / 2
    safety = env.barrier.si_radius / 2 if env.barrier is not None else None
    for i, (x, y, theta) in enumerate(poses):
        colour = AGENT_COLOURS[i % len(AGENT_COLOURS)]
        ax.add_patch(plt.Circle((x, y), radius, color=colour, alpha=0.85))
        ax.plot([x, x + 1.3 * radius * np.cos(theta)], [y, y + 1.3 * radius * np.sin(theta)], color="black", lw=1.5)
        if safety is not None:
            px, py = x + 0.05 * np.cos(theta), y + 0.05 * np.sin(theta)
            ax.add_patch(plt.Circle((px, py), safety, fill=False, lw=0.5, ls=":", color=colour))
        ax.text(x, y, str(i), ha="center", va="center", fontsize=7, color="white")
    title = env.name.replace("_", " ")
    if step is not None:
        title += f"   step {step}"
    if reward is not None:
        title += f"   return {reward:.2f}"
    ax.set_title(title, fontsize=9)
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    return image


def render_episode(env, policy, key, max_steps: int | None = None) -> list[np.ndarray]:
    """Frames of one episode (reset frame + one per step, stopping at ``done``).

    ``policy(key, obs [N, obs_dim]) -> actions [N]``; ``None`` means uniform random actions.
    """
    import jax

    step = jax.jit(env.step_env)
    act = jax.jit(policy) if policy is not None else jax.jit(
        lambda k, obs: jax.random.randint(k, (env.num_agents,), 0, env.num_actions))
    key, k_reset = jax.random.split(key)
    obs, state = env.reset(k_reset)
    frames = [render_frame(env, jax.device_get(state), step=0, reward=0.0)]
    for t in range(max_steps or env.max_steps):
        key, k_act, k_step = jax.random.split(key, 3)
        obs, state, rewards, done, info = step(k_step, state, act(k_act, obs))
        frames.append(render_frame(env, jax.device_get(state), step=t + 1, reward=float(info["episode_return"])))
        if bool(done):
            break
    return frames


def _draw_layer(ax, plt, layer: dict) -> None:
    kind = layer["kind"]
    if kind == "points":
        pts = np.asarray(layer["xy"], dtype=float).reshape(-1, 2)
        ax.scatter(pts[:, 0], pts[:, 1], s=layer.get("size", 40), marker=layer.get("marker", "o"),
                   c=layer.get("color", "black"), alpha=layer.get("alpha", 1.0), zorder=3)
    elif kind == "rect":
        x0, y0, w, h = layer["xywh"]
        ax.add_patch(plt.Rectangle((x0, y0), w, h, color=layer.get("color", "grey"), alpha=layer.get("alpha", 0.25), lw=0))
    elif kind == "circle":
        (x, y), r = layer["xy"], layer["r"]
        ax.add_patch(plt.Circle((x, y), r, color=layer.get("color", "grey"), alpha=layer.get("alpha", 0.25), lw=0))
    elif kind == "text":
        x, y = layer["xy"]
        ax.text(x, y, layer["text"], fontsize=layer.get("size", 8), ha="center", va="center")
    elif kind == "image":
        ax.imshow(layer["rgb"], extent=layer["extent"], alpha=layer.get("alpha", 0.5), zorder=0, interpolation="nearest")
    else:
        raise ValueError(f"unknown render layer kind {kind!r}")
