"""The browser viewer (viser): the avatar's rig, its page, and the training panel of `train --view`."""
