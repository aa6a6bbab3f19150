"""The paper's experiments, their reports and figures."""
