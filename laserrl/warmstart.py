"""Warm-starting a Q-network from a checkpoint."""
from __future__ import annotations

from laserrl.agents.qnet import FieldQNet
from laserrl.checkpoint import CheckpointError, load_checkpoint


def warm_start(qnet: FieldQNet, checkpoint: str) -> dict:
    """Copy a checkpoint's Q-network weights into ``qnet`` (same architecture and head).

    A head of another size (a checkpoint of another stage) is refused with a clear error.
    """
    state = load_checkpoint(checkpoint)
    if int(state["num_actions"]) != qnet.num_actions:
        raise CheckpointError(
            f"checkpoint {state['path']} has a {state['num_actions']}-action head (stage {state.get('stage')}); "
            f"this task needs {qnet.num_actions} actions"
        )
    try:
        qnet.load_state_dict(state["qnet"])
    except RuntimeError as err:
        raise CheckpointError(f"checkpoint {state['path']} does not match this network: {str(err).splitlines()[0]}") from None
    return state
