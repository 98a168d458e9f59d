"""Physics-based model inputs: what the scene's geometry and elasticity say about a frame,
computed outright and given to the network as node inputs (``graph.penetration``,
``graph.clearance``, ``graph.elastic``), apart from the bi-stride hierarchy (:mod:`bsms.graph`)
they are read on.

- :mod:`bsms.physics.penetration`: how far moving obstacles reach into the body
  (:class:`~bsms.physics.penetration.Penetration`) and where the container's walls are per node
  (:class:`~bsms.physics.penetration.Clearance`);
- :mod:`bsms.physics.elastic`: the body's linear-elastic answer to that push, a finite-element
  solve on its rest mesh (:class:`~bsms.physics.elastic.ElasticResponse`).
"""
