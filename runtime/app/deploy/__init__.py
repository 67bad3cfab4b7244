"""Deployment to the robot's computer: the offline bundle (`dct deploy bundle`), its install
script and systemd unit (templates.py), and the systemd notification the controller sends
(sd_notify.py). Importing this package imports nothing heavy."""
