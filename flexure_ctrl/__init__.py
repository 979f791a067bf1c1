"""flexure_ctrl: look-up-table feedforward control of a bearing-free two-link flexure arm."""

__version__ = '0.1.0'
