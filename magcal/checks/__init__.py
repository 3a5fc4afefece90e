"""What the data say before any model is fitted: quality findings, direction coverage, the noise floor and the
reference field."""
