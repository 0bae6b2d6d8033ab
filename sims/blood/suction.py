"""What every bleeding method takes of a step's suction tools."""

MAX_SUCTION_TOOLS = 8  # suction tools a bleeding method serves in one step


def active_suction(suction) -> list:
    """The suction tools of a step's `suction` list that take blood (rate above 0), at most MAX_SUCTION_TOOLS."""
    return [tool for tool in suction if tool[2] > 0][:MAX_SUCTION_TOOLS]
