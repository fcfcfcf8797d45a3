"""uwcam: underwater ranging camera software.

Water absorbs red light far faster than green or blue, so the ratio of colour
channels at a pixel tells how far the light travelled. uwcam turns a colour
camera and a lamp into a per-pixel range sensor. See docs/physics.md for the physics.
"""

__version__ = "0.1.0"
