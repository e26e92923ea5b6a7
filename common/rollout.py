"""A goal task's success flag in an episode's ``info``: Fetch's and the Shadow hand's
``is_success``, the mazes' ``success``. (The scripts' rollouts read it inline.)"""

SUCCESS_KEYS = ("is_success", "success")


def success_of(info: dict):
    """A goal task's success flag in ``info`` (per env in a vector env's), else None."""
    return next((info[key] for key in SUCCESS_KEYS if key in info), None)
