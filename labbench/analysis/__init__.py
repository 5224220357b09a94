"""Analysis of recorded force and position: loading, identification of the
device (mass, damping, friction) and closed-loop frequency response (ETFE).

No Qt here; heavy optional pieces (cvxpy, matplotlib) are imported lazily.
"""
