"""The one error model every stage of refine scores a block with (docs/method.md, "The error
model"): GNSS as white noise, a bias common to the block and a slowly varying part along the
track (`gnss`), and the tie points' distances to the surfaces that can carry them, faces and
terrain, each face's points sharing its error (`score`)."""
