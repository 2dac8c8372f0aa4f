"""The station: a cell's instruments, its campaign store and its operator wired into one Session.

Below both front ends, the command line (`hil run`, `hil demo`) and the browser console (`hil serve`): each
opens its session here and adds only what is its own (the terminal's Ctrl-C, the page's prompts).
"""
