"""A vector env's state as plain values, so that a resumed run goes on mid-episode where it
stopped, as if never stopped (``EnvsState``, saved in ``resume.pt`` by ``common/run.py``).

Per env, each layer's (the wrappers' and the task's) numbers, arrays (and dicts of arrays) and
random generators, and a MuJoCo task's physics (``mjSTATE_INTEGRATION`` and what its last step
computed) are saved; what a task keeps in other containers (a list) is not.

The vector env's last observations, which a resumed run starts from, have no public API in
gymnasium 1.4.0: ``SyncVectorEnv`` keeps them in its private ``_observations``, which ``reset``
and ``step`` fill and return (a copy, by default). ``EnvsState`` reads and sets them there;
``test_the_vector_envs_private_observations_are_its_last_ones`` (tests/test_resume.py) fails if a
gymnasium release renames it or changes what it holds. The scripts' vector envs reset an ended
episode in the step that ends it (``SAME_STEP``), so no reset is pending between two steps; a
``NEXT_STEP`` vector env's pending resets (its private ``_autoreset_envs``) are not saved.
"""

import copy

import numpy as np


class EnvsState:
    """A ``SyncVectorEnv``'s state: ``state_dict`` as plain values, for ``resume.pt``;
    ``load_state_dict`` into freshly made envs of the same task and wrappers."""

    def __init__(self, envs):
        self.envs = envs

    def state_dict(self) -> dict:
        layers = [[_layer_state(layer) for layer in _layers(env)] for env in self.envs.envs]
        return {"layers": layers, "observations": copy.deepcopy(self.envs._observations)}

    def load_state_dict(self, state: dict) -> None:
        for env, saved in zip(self.envs.envs, state["layers"], strict=True):
            for layer, values in zip(_layers(env), saved, strict=True):
                for name, value in values.items():
                    _restore_value(layer, name, value)
        self.envs._observations = state["observations"]

    def observations(self):
        """The observations the envs stopped in, as a step returns them."""
        return copy.deepcopy(self.envs._observations)


def _layers(env) -> list:
    """An env's wrappers, outermost first, then the task itself, then the envs a layer drives
    (the mazes' ``point_env``, whose physics is the task's), in the order of their attributes."""
    import gymnasium as gym

    layers = [env]
    for layer in layers:  # grows as it goes
        inner = [layer.env] if hasattr(layer, "env") else []
        for v in inner + [v for v in vars(layer).values() if isinstance(v, gym.Env)]:
            if all(v is not seen for seen in layers):  # once each: a wrapper's env is also among its attributes
                layers.append(v)
    return layers


def _layer_state(layer) -> dict:
    state = {}
    for name, value in vars(layer).items():
        if isinstance(value, np.random.Generator):
            state[name] = {"generator": value.bit_generator.state}
        elif type(value).__name__ == "MjData":
            state[name] = {"mujoco": _physics(layer.model, value)}
        elif isinstance(value, bool | int | float | np.ndarray | np.generic | None) or (
            isinstance(value, dict) and value and all(isinstance(v, np.ndarray) for v in value.values())
        ):  # a dict of arrays: a recorded state (common/grasped_start.py)
            state[name] = copy.deepcopy(value)
    return state


def _restore_value(layer, name: str, value) -> None:
    if isinstance(value, dict) and value.keys() == {"generator"}:
        generator = getattr(layer, name, None) or np.random.default_rng()
        generator.bit_generator.state = value["generator"]
        setattr(layer, name, generator)
    elif isinstance(value, dict) and value.keys() == {"mujoco"}:
        _restore_physics(layer.model, getattr(layer, name), value["mujoco"])
    else:
        setattr(layer, name, value)


# what a MuJoCo step leaves computed (positions, orientations, velocities, forces), which a task
# may read before its next step (the Fetch tasks' mocap reads the gripper's body position)
COMPUTED = (
    "xpos",
    "xquat",
    "xmat",
    "xipos",
    "ximat",
    "xanchor",
    "xaxis",
    "geom_xpos",
    "geom_xmat",
    "site_xpos",
    "site_xmat",
    "cam_xpos",
    "cam_xmat",
    "light_xpos",
    "light_xdir",
    "subtree_com",
    "cdof",
    "cinert",
    "cvel",
    "cdof_dot",
    "cacc",
    "cfrc_int",
    "cfrc_ext",
    "sensordata",
    "actuator_length",
    "actuator_velocity",
    "actuator_force",
    "ten_length",
    "ten_velocity",
    "qfrc_actuator",
    "qfrc_bias",
    "qfrc_passive",
    "qfrc_constraint",
    "qacc",
    "energy",
)


def _physics(model, data) -> dict:
    """MuJoCo's state (``mjSTATE_INTEGRATION``) and, in one array, what the last step computed
    from it (``COMPUTED``)."""
    import mujoco

    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    computed = [np.ravel(getattr(data, name)) for name in COMPUTED if hasattr(data, name)]
    return {"state": state, "computed": np.concatenate(computed)}


def _restore_physics(model, data, saved: dict) -> None:
    import mujoco

    mujoco.mj_setState(model, data, saved["state"], mujoco.mjtState.mjSTATE_INTEGRATION)
    mujoco.mj_forward(model, data)  # what COMPUTED leaves out, then COMPUTED as it was
    start = 0
    for name in (name for name in COMPUTED if hasattr(data, name)):
        array = getattr(data, name)
        array.flat[:] = saved["computed"][start : start + array.size]
        start += array.size
    if start != len(saved["computed"]):
        raise ValueError(f"the saved physics holds {len(saved['computed'])} computed values, this task {start}")
