"""Finding and following a person with a 3-D sensor: the ground taken away (standing), what stands
on it judged by its shape (person), the candidates of one cloud (detect), and one target followed by
a constant-velocity Kalman filter with gating (kalman). Arrays in, arrays out; no devices."""
