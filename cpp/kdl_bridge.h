// C++ side of the kinematics bridge: a KDL chain built once from a URDF, and an
// allocation-free forward kinematics + geometric Jacobian in one pass.
#pragma once
#include <memory>
#include <string>
#include <vector>

#include <kdl/chain.hpp>
#include <kdl/frames.hpp>

#include "rust/cxx.h"

namespace trocar_docking {

class KdlChain {
 public:
  KdlChain(KDL::Chain chain, std::vector<std::string> names, std::vector<double> lower,
           std::vector<double> upper, std::vector<double> velocity, std::vector<double> effort);
  // Number of movable joints.
  size_t n_joints() const;
  rust::Vec<rust::String> joint_names() const;
  rust::Vec<double> lower() const;
  rust::Vec<double> upper() const;
  rust::Vec<double> velocity() const;
  rust::Vec<double> effort() const;
  // Tip pose: pose[0..3] position, pose[3..12] rotation row-major. Jacobian 6 x n,
  // column-major, rows (vx vy vz wx wy wz), base frame, reference point at the tip.
  // Throws std::invalid_argument (an Err in Rust) unless q has n_joints(), pose 12 and jac
  // 6 n_joints() values: the Rust side checks the same, and neither trusts the other.
  // Allocates nothing unless it throws.
  void fk_jacobian(rust::Slice<const double> q, rust::Slice<double> pose,
                   rust::Slice<double> jac) const;
  void fk(rust::Slice<const double> q, rust::Slice<double> pose) const;

 private:
  // Per-segment data copied out of KDL at construction. KDL's Joint::pose caches its last
  // result in mutable members, so calling it from two threads races; the hot path below
  // uses only these immutable copies, which makes a KdlChain safe to share between threads.
  enum class Kind { Fixed, Revolute, Prismatic };
  struct Seg {
    Kind kind;
    KDL::Vector axis;    // joint axis, in the segment's parent frame
    KDL::Vector origin;  // joint origin, in the segment's parent frame
    KDL::Frame tip;      // segment frame at q = 0 (the URDF joint origin)
  };
  std::vector<Seg> segs_;
  KDL::Frame joint_frame(const Seg& s, double q) const;
  KDL::Chain chain_;
  std::vector<std::string> names_;
  std::vector<double> lower_, upper_, velocity_, effort_;
};

// Parse `urdf_xml` and build the chain from `base` to `tip`. Throws std::runtime_error
// (which cxx turns into a Rust Err) on a malformed URDF or an unknown link.
std::unique_ptr<KdlChain> kdl_chain_from_urdf(rust::Str urdf_xml, rust::Str base, rust::Str tip);

}  // namespace trocar_docking
