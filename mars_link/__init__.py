"""mars-link: software-in-the-loop flight stack for Modular Aerial Robotic Systems."""

__version__ = "0.1.0"
