"""Control studies: C3 (``lcs_cvx.control``) in closed loop on C3's cart-pole with soft walls."""
