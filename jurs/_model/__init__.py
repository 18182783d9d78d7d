"""The model: the uniform cubic B-spline basis, the rational implicit function g (eq. 14)
and its evaluation on lattices, and saving and loading fitted splines."""
