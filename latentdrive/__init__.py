"""latentdrive: generalizable driving policies from restricted latent representations."""

__version__ = "0.1.0"
