"""Match drawings (``topoloc show-match``): a query beside the map place it matched, labelled.

Layer 4, beside :mod:`topoloc.evaluation`: it takes a fitted recogniser, its
map traverses and resources and returns pixels (or writes a PNG).

:mod:`~topoloc.drawing.match_figure`
    Labelled drawings for any method (:func:`~topoloc.drawing.match_figure.labelled_match`).
:mod:`~topoloc.drawing.show_match`
    The Cooc-Map paper's Fig. 1 and 5: a method's declared consistent group
    (:class:`~topoloc.drawing.show_match.GroupMatcher`) joined to a map image.
"""
