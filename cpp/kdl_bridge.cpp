#include "trocar_docking/cpp/kdl_bridge.h"

#include <limits>
#include <stdexcept>
#include <string>

#include <mutex>

#include <console_bridge/console.h>
#include <kdl/frames.hpp>
#include <kdl/tree.hpp>
#include <kdl_parser/kdl_parser.hpp>
#include <urdf_parser/urdf_parser.h>

namespace trocar_docking {

KdlChain::KdlChain(KDL::Chain chain, std::vector<std::string> names, std::vector<double> lower,
                   std::vector<double> upper, std::vector<double> velocity,
                   std::vector<double> effort)
    : chain_(std::move(chain)),
      names_(std::move(names)),
      lower_(std::move(lower)),
      upper_(std::move(upper)),
      velocity_(std::move(velocity)),
      effort_(std::move(effort)) {
  for (const auto& seg : chain_.segments) {
    const KDL::Joint& joint = seg.getJoint();
    Seg s;
    const int type = joint.getType();
    s.kind = type == KDL::Joint::None ? Kind::Fixed
             : type >= KDL::Joint::TransAxis ? Kind::Prismatic
                                             : Kind::Revolute;
    s.axis = joint.JointAxis();
    s.origin = joint.JointOrigin();
    s.tip = seg.getFrameToTip();
    // The closed forms below assume KDL's default joint scale 1 and offset 0 (kdl_parser
    // sets neither); refuse a chain where the segment pose disagrees with them.
    for (double q : {0.0, 0.7}) {
      if (!KDL::Equal(seg.pose(q), joint_frame(s, q) * s.tip, 1e-12))
        throw std::runtime_error("joint '" + joint.getName() + "' has a scale or offset this bridge does not support");
    }
    segs_.push_back(s);
  }
}

KDL::Frame KdlChain::joint_frame(const Seg& s, double q) const {
  switch (s.kind) {
    case Kind::Revolute: {
      const KDL::Rotation r = KDL::Rotation::Rot2(s.axis, q);
      return KDL::Frame(r, s.origin - r * s.origin);
    }
    case Kind::Prismatic:
      return KDL::Frame(s.axis * q);
    default:
      return KDL::Frame::Identity();
  }
}

size_t KdlChain::n_joints() const { return chain_.getNrOfJoints(); }

static rust::Vec<double> to_vec(const std::vector<double>& v) {
  rust::Vec<double> out;
  out.reserve(v.size());
  for (double x : v) out.push_back(x);
  return out;
}

rust::Vec<rust::String> KdlChain::joint_names() const {
  rust::Vec<rust::String> out;
  for (const auto& n : names_) out.push_back(rust::String(n));
  return out;
}
rust::Vec<double> KdlChain::lower() const { return to_vec(lower_); }
rust::Vec<double> KdlChain::upper() const { return to_vec(upper_); }
rust::Vec<double> KdlChain::velocity() const { return to_vec(velocity_); }
rust::Vec<double> KdlChain::effort() const { return to_vec(effort_); }

static void write_pose(const KDL::Frame& f, rust::Slice<double> pose) {
  pose[0] = f.p.x();
  pose[1] = f.p.y();
  pose[2] = f.p.z();
  for (int i = 0; i < 9; ++i) pose[3 + i] = f.M.data[i];
}

namespace {
// The lengths fk and fk_jacobian index with, checked before any access.
void check_lengths(size_t joints, rust::Slice<const double> q, rust::Slice<double> pose) {
  if (q.size() != joints)
    throw std::invalid_argument("wrong joint count: the chain has " + std::to_string(joints) + " joints, got " +
                                std::to_string(q.size()));
  if (pose.size() != 12)
    throw std::invalid_argument("pose buffer must hold 12 values, got " + std::to_string(pose.size()));
}
}  // namespace

void KdlChain::fk(rust::Slice<const double> q, rust::Slice<double> pose) const {
  check_lengths(n_joints(), q, pose);
  KDL::Frame t = KDL::Frame::Identity();
  unsigned j = 0;
  for (const auto& s : segs_) {
    t = s.kind == Kind::Fixed ? t * s.tip : t * joint_frame(s, q[j++]) * s.tip;
  }
  write_pose(t, pose);
}

void KdlChain::fk_jacobian(rust::Slice<const double> q, rust::Slice<double> pose,
                           rust::Slice<double> jac) const {
  check_lengths(n_joints(), q, pose);
  if (jac.size() != 6 * n_joints())
    throw std::invalid_argument("Jacobian buffer must hold 6 x " + std::to_string(n_joints()) + " values, got " +
                                std::to_string(jac.size()));
  // One pass down the chain: store each joint's axis (angular rows) and origin (linear
  // rows) in the base frame, then turn the origins into lever arms once the tip is known.
  KDL::Frame t = KDL::Frame::Identity();
  unsigned j = 0;
  double* J = jac.data();
  for (const auto& s : segs_) {
    if (s.kind == Kind::Fixed) {
      t = t * s.tip;
      continue;
    }
    const KDL::Vector axis = t.M * s.axis;
    const KDL::Vector origin = t * s.origin;
    double* c = J + 6 * j;
    const bool prismatic = s.kind == Kind::Prismatic;
    c[0] = origin.x();
    c[1] = origin.y();
    c[2] = origin.z();
    c[3] = axis.x();
    c[4] = axis.y();
    c[5] = axis.z();
    if (prismatic) c[0] = std::numeric_limits<double>::quiet_NaN();  // marker, fixed below
    t = t * joint_frame(s, q[j]) * s.tip;
    ++j;
  }
  write_pose(t, pose);
  const double px = t.p.x(), py = t.p.y(), pz = t.p.z();
  for (unsigned k = 0; k < j; ++k) {
    double* c = J + 6 * k;
    const double ax = c[3], ay = c[4], az = c[5];
    if (c[0] != c[0]) {  // prismatic: linear column is the axis, no angular part
      c[0] = ax;
      c[1] = ay;
      c[2] = az;
      c[3] = c[4] = c[5] = 0.0;
      continue;
    }
    const double rx = px - c[0], ry = py - c[1], rz = pz - c[2];
    c[0] = ay * rz - az * ry;
    c[1] = az * rx - ax * rz;
    c[2] = ax * ry - ay * rx;
  }
}

namespace {
// Collects what urdfdom and kdl_parser log while parsing, so that it reaches the Rust error
// instead of the console.
class CaptureHandler : public console_bridge::OutputHandler {
 public:
  void log(const std::string& text, console_bridge::LogLevel level, const char*, int) override {
    if (level < console_bridge::CONSOLE_BRIDGE_LOG_WARN) return;
    if (!text_.empty()) text_ += "; ";
    text_ += text;
  }
  const std::string& text() const { return text_; }

 private:
  std::string text_;
};
std::mutex console_mutex;  // the console_bridge handler is process-global
}  // namespace

std::unique_ptr<KdlChain> kdl_chain_from_urdf(rust::Str urdf_xml, rust::Str base, rust::Str tip) {
  const std::string xml(urdf_xml);
  urdf::ModelInterfaceSharedPtr model;
  KDL::Tree tree;
  bool tree_ok = false;
  std::string log;
  {
    std::lock_guard<std::mutex> lock(console_mutex);
    CaptureHandler capture;
    console_bridge::useOutputHandler(&capture);
    try {
      model = urdf::parseURDF(xml);
      if (model) tree_ok = kdl_parser::treeFromUrdfModel(*model, tree);
    } catch (const std::exception& e) {
      log = capture.text();
      console_bridge::restorePreviousOutputHandler();
      throw std::runtime_error(std::string("malformed URDF: ") + e.what() + (log.empty() ? "" : " (" + log + ")"));
    }
    log = capture.text();
    console_bridge::restorePreviousOutputHandler();
  }
  const std::string detail = log.empty() ? "" : " (" + log + ")";
  if (!model) throw std::runtime_error("malformed URDF: urdfdom could not parse it" + detail);
  if (!tree_ok) throw std::runtime_error("URDF could not be turned into a KDL tree" + detail);
  const std::string b(base), t(tip);
  if (tree.getSegments().count(b) == 0 && tree.getRootSegment()->first != b)
    throw std::runtime_error("unknown base link '" + b + "'");
  if (tree.getSegments().count(t) == 0) throw std::runtime_error("unknown tip link '" + t + "'");
  KDL::Chain chain;
  if (!tree.getChain(b, t, chain))
    throw std::runtime_error("no chain from '" + b + "' to '" + t + "'");
  std::vector<std::string> names;
  std::vector<double> lower, upper, velocity, effort;
  const double inf = std::numeric_limits<double>::infinity();
  for (const auto& seg : chain.segments) {
    const KDL::Joint& joint = seg.getJoint();
    if (joint.getType() == KDL::Joint::None) continue;
    // A chain walked towards the root would invert joints; refuse it rather than lie.
    auto uj = model->getJoint(joint.getName());
    if (!uj) throw std::runtime_error("joint '" + joint.getName() + "' not found in URDF");
    if (uj->child_link_name != seg.getName())
      throw std::runtime_error("chain from '" + b + "' to '" + t +
                               "' runs against joint directions; base must be an ancestor of tip");
    names.push_back(joint.getName());
    if (uj->limits && uj->type != urdf::Joint::CONTINUOUS) {
      lower.push_back(uj->limits->lower);
      upper.push_back(uj->limits->upper);
    } else {
      lower.push_back(-inf);
      upper.push_back(inf);
    }
    velocity.push_back(uj->limits && uj->limits->velocity > 0 ? uj->limits->velocity : inf);
    effort.push_back(uj->limits && uj->limits->effort > 0 ? uj->limits->effort : inf);
  }
  return std::make_unique<KdlChain>(std::move(chain), std::move(names), std::move(lower),
                                    std::move(upper), std::move(velocity), std::move(effort));
}

}  // namespace trocar_docking
