"""Cards whose contents reach the browser when first opened.

A page's server cost is mostly the Bokeh models Panel makes for it (about 1 ms each, 300+ on the
dashboard; see the review issue's "sessions are cheap"), and a collapsed card's models are made
and sent even though nobody sees them until the card is opened. :func:`lazy_card` keeps the
Python objects (widgets keep their values and watchers, code may read and set them) and puts
them into the card only when a user first opens it: the models are then made for that page alone.
Given a ``build`` function instead, it makes the Python objects then too (the settings cards:
their widgets follow the pipeline, which holds the values, so nothing needs them before).
"""

from __future__ import annotations

import panel as pn

__all__ = ["lazy_card", "fill"]


def lazy_card(*objects, build=None, collapsed: bool = True, **params) -> pn.Card:
    """A :class:`panel.Card` of ``objects``; when ``collapsed`` it starts empty and takes them the
    first time it is opened (in the browser or by setting ``card.collapsed = False``).

    ``build``: a function returning the objects instead, called when they are first needed — the
    Python objects too are made then (each Panel object costs a page ~25 KB of server memory even
    unseen: its parameters' watchers, and a pane's own layout)."""
    if build is not None and objects:
        raise ValueError("lazy_card: give objects or build, not both")
    if not collapsed:
        return pn.Card(*(build() if build is not None else objects), collapsed=False, **params)
    card = pn.Card(collapsed=True, **params)
    card._lazy_objects = build if build is not None else list(objects)

    def _open(event):
        if not event.new:
            fill(card)

    card._lazy_watcher = card.param.watch(_open, "collapsed")
    return card


def fill(card: pn.Card) -> pn.Card:
    """Put a lazy card's objects into it now (a no-op for a card already filled or not lazy)."""
    objects = getattr(card, "_lazy_objects", None)
    if objects is not None:
        card._lazy_objects = None
        card.param.unwatch(card._lazy_watcher)
        card.objects = objects() if callable(objects) else objects
    return card
